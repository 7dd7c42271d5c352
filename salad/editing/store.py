"""Capture of cross-attention maps during generation, with bounded memory.

The store keeps, for the chosen rows of the batch, the head-averaged cross-attention
of every (diffusion step, layer) it is asked to watch, at latent resolution
(T/4 frames x 7 body parts x text tokens) in float16: a few MB for a 10 s motion,
independent of the number of heads and never the full per-head, per-query maps.
Afterwards any layer subset and step range can be aggregated without re-running.
"""
from __future__ import annotations

from contextlib import ExitStack, contextmanager
from dataclasses import dataclass

import numpy as np
import torch

from ..models.attention import CROSS, AttentionCall


@dataclass
class AttentionMaps:
    """Cross-attention of one generated motion, words x body parts x time.

    data: (steps, layers, words, 7, latent frames) float32, head-averaged, sub-word
    tokens summed into their word.
    """

    words: list[str]
    data: np.ndarray
    frames: int
    layers: list[int]

    @property
    def steps(self) -> int:
        return self.data.shape[0]

    def aggregate(self, layers: list[int] | None = None, steps: tuple[int, int] | None = None,
                  at_latent_rate: bool = False) -> np.ndarray:
        """Mean over the chosen layers and step range [start, stop) -> (words, 7, frames)."""
        lsel = [self.layers.index(l) for l in layers] if layers is not None else slice(None)
        s0, s1 = steps if steps is not None else (0, self.steps)
        if not 0 <= s0 < s1 <= self.steps:
            raise ValueError(f"step range must satisfy 0 <= start < stop <= {self.steps}, got {steps}")
        m = self.data[s0:s1][:, lsel].mean(axis=(0, 1))
        return m if at_latent_rate else to_motion_rate(m, self.frames)

    def word(self, word: str | int, **kw) -> np.ndarray:
        """(7, frames) map of one word, by index or by text (first occurrence)."""
        i = word if isinstance(word, int) else self.words.index(word)
        return self.aggregate(**kw)[i]


def to_motion_rate(m: np.ndarray, frames: int) -> np.ndarray:
    """Latent frames (..., T') -> motion frames (..., frames): latent frame k covers motion
    frames 4k..4k+3, so values are interpolated at those frames' centres."""
    Tl = m.shape[-1]
    centres = (np.arange(frames) + 0.5) / 4.0 - 0.5
    centres = np.clip(centres, 0, Tl - 1)
    lo = np.floor(centres).astype(int)
    hi = np.minimum(lo + 1, Tl - 1)
    w = centres - lo
    return m[..., lo] * (1 - w) + m[..., hi] * w


class StepCounter:
    """Counts denoising steps: a step starts at every call of the first attention module."""

    def __init__(self, total_steps: int = 0):
        self.total = total_steps
        self.step = -1
        self._first: tuple[str, int] | None = None

    def see(self, call: AttentionCall) -> None:
        self.tick(call.kind, call.layer)

    def tick(self, kind: str, layer: int) -> None:
        key = (kind, layer)
        if self._first is None:
            self._first = key
        if key == self._first:
            self.step += 1

    @property
    def fraction(self) -> float:
        """Share of the denoising done before this step (0 at the first step)."""
        return max(self.step, 0) / max(self.total, 1)


def call_rows(call: AttentionCall, motions: slice) -> slice:
    """The rows of call.probs that belong to the batch's motions `motions`: one per motion in
    cross-attention, one per body part (temporal) or latent frame (skeletal) in self-attention."""
    per = 1 if call.kind == CROSS else call.parts if call.kind == "temporal" else call.frames
    return slice(motions.start * per, motions.stop * per)


class RowAddressed:
    """A controller that addresses rows of the full batched forward [unconditional..., conditional...].
    Steps without guidance need the conditional rows alone (Pipeline.model_fn): while they run,
    inside leading_rows_dropped(n), every row it addresses, and every row its `observers` (controllers
    it passes the maps on to) address, sits n places lower."""

    _dropped = 0
    observers: tuple | list = ()

    def own_lowest_row(self) -> int:
        raise NotImplementedError

    def lowest_row(self) -> int:
        return min([self.own_lowest_row(), *(o.lowest_row() for o in self.observers if isinstance(o, RowAddressed))])

    def at(self, rows: slice) -> slice:
        """Where `rows` of the full layout are in the forward now running."""
        return slice(rows.start - self._dropped, rows.stop - self._dropped)

    @contextmanager
    def leading_rows_dropped(self, n: int):
        if n > self.lowest_row():
            raise ValueError(f"{type(self).__name__} reads row {self.lowest_row()}, which a forward without the "
                             f"first {n} rows lacks")
        with ExitStack() as stack:
            for o in self.observers:
                if isinstance(o, RowAddressed):
                    stack.enter_context(o.leading_rows_dropped(n))
            self._dropped = n
            try:
                yield
            finally:
                self._dropped = 0


class AttentionStore(RowAddressed):
    """A controller that observes (and never changes) cross-attention maps.

    rows: which batch rows (of the batched CFG forward) to keep, e.g. the conditional
    ones; layers / steps restrict what is captured.
    """

    def __init__(self, text, rows: slice, frames: int, layers: list[int] | None = None,
                 steps: tuple[int, int] | None = None):
        self.text, self.rows, self.frames = text, rows, frames
        self.layer_filter = set(layers) if layers is not None else None
        self.step_range = steps
        # fed cross-attention calls only: a step starts at the first cross-attention layer,
        # one map set per network evaluation
        self.counter = StepCounter()
        self._current: dict[int, torch.Tensor] = {}
        self.captured: list[dict[int, torch.Tensor]] = []

    def __call__(self, call: AttentionCall) -> torch.Tensor:
        if call.kind != CROSS:
            return call.probs
        step = self.counter.step
        self.counter.see(call)
        if self.counter.step != step:
            self._flush()
        if self.layer_filter is not None and call.layer not in self.layer_filter:
            return call.probs
        if self.step_range is not None and not self.step_range[0] <= self.counter.step < self.step_range[1]:
            return call.probs
        p = call.probs[self.at(self.rows)].float().mean(dim=1)     # (b, T*J, L), head mean
        b, q, L = p.shape
        self._current[call.layer] = p.reshape(b, call.frames, call.parts, L).to(torch.float16)
        return call.probs

    def own_lowest_row(self) -> int:
        return self.rows.start

    def _flush(self) -> None:
        if self._current:
            self.captured.append(self._current)
            self._current = {}

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for d in self.captured + [self._current] for t in d.values())

    def maps(self, row: int, frames: int | None = None) -> AttentionMaps:
        """Word-level maps of one motion of the batch (row index within `rows`)."""
        self._flush()
        if not self.captured:
            raise RuntimeError("no attention was captured")
        layers = sorted(self.captured[0])
        text_row = range(self.text.tokens.shape[0])[self.rows][row]
        words = self.text.words[text_row]
        tw = self.text.token_words[text_row].cpu()                # (L,) word index or -1
        L = tw.shape[0]
        merge = torch.zeros(L, max(len(words), 1))
        for k in range(L):
            if tw[k] >= 0:
                merge[k, tw[k]] = 1.0
        data = np.zeros((len(self.captured), len(layers), len(words), 7, self.captured[0][layers[0]].shape[1]),
                        dtype=np.float32)
        for s, per_layer in enumerate(self.captured):
            for li, layer in enumerate(layers):
                m = per_layer[layer][row].float().cpu()           # (T', J, L)
                w = m[..., :L] @ merge                            # (T', J, words)
                data[s, li] = w.permute(2, 1, 0).numpy()[: len(words)]
        return AttentionMaps(words=list(words), data=data, frames=frames or self.frames, layers=layers)
