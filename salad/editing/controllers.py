"""Attention controllers that edit motion by modulating attention maps (SALAD §3.3, supp. B).

The source and the target branch run in one batched forward from the same initial
noise; with classifier-free guidance the rows are

    [source uncond, target uncond, source cond, target cond]   (x batch each)

Only the conditional target rows are changed, as in Prompt-to-Prompt. Each rule is a
small class; `AttentionEdit` runs one base rule (swap, refine or keep) on the
cross-attention, then any number of map transforms (re-weighting, mirroring), and
injects the source's self-attention maps early on.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from ..models.attention import CROSS, AttentionCall
from ..motion import skeleton as sk
from .align import TokenAlignment
from .spec import DEFAULT_SELF_INJECT, DEFAULT_TAU
from .store import RowAddressed, StepCounter, call_rows


@dataclass
class Rows:
    """Where the branches sit in the batched forward (each a slice of batch rows)."""

    source: slice | None      # None: the source is a replayed run, not rows of the forward
    target: slice


def cfg_rows(batch: int) -> Rows:
    """Rows of the conditional source and target branches in the CFG layout above."""
    return Rows(source=slice(2 * batch, 3 * batch), target=slice(3 * batch, 4 * batch))


# ---------------------------------------------------------------- cross-attention rules
# A rule maps (source map, target map), each (b, heads, T, J, L), to the target's new map.


class KeepSource:
    """Mirroring and re-weighting on an unchanged prompt start from the source's map."""

    def __call__(self, src, tgt, progress: float):
        return src


class WordSwap:
    """Source maps while t >= tau (the early steps), the target's own maps after.
    tau is a fraction of T: 0.8 means the first 20% of the steps follow the source.

    own_replaced: the swapped words keep their own maps in the source-led steps too. Where the
    source leads for a single step (a few-step sampler), that step lays out the whole motion, and
    the new word attending where the old one did pulls it halfway back to the source: the
    student's "walks and turns right" -> "left" ended at -26° to -40° (source about -90°, target +70°)."""

    def __init__(self, alignment: TokenAlignment, tau: float = DEFAULT_TAU["swap"], own_replaced: bool = False):
        if not 0.0 <= tau <= 1.0:
            raise ValueError(f"tau must be in [0, 1], got {tau}")
        self.alignment, self.tau, self.own_replaced = alignment, tau, own_replaced

    def __call__(self, src, tgt, progress: float):
        if progress < 1.0 - self.tau:
            mapped = self.alignment.apply(src)
            if self.own_replaced:
                return torch.where(self.alignment.replaced.to(tgt.device), tgt, mapped)
            return mapped
        return tgt


class Refine:
    """Target tokens aligned to a source token take its map; new tokens keep their own.
    Applied while t >= tau (tau = 0 means every step)."""

    def __init__(self, alignment: TokenAlignment, tau: float = DEFAULT_TAU["refine"]):
        if not 0.0 <= tau <= 1.0:
            raise ValueError(f"tau must be in [0, 1], got {tau}")
        self.alignment, self.tau = alignment, tau

    def __call__(self, src, tgt, progress: float):
        if progress >= 1.0 - self.tau:
            return tgt
        mapped = self.alignment.apply(src)
        new = self.alignment.inserted.to(tgt.device)
        return torch.where(new, tgt, mapped)


# ---------------------------------------------------------------- map transforms


class Reweight:
    """Scale the attention of the given token positions by s (not renormalised, so s
    can amplify, weaken or, below zero, invert a word's influence)."""

    def __init__(self, tokens: list[int], scale: float):
        if not -3.0 <= scale <= 3.0:
            raise ValueError(f"re-weighting scale must be in [-3, 3], got {scale}")
        if not tokens:
            raise ValueError("re-weighting needs at least one word of the prompt")
        self.tokens, self.scale = list(tokens), float(scale)

    def __call__(self, m: torch.Tensor) -> torch.Tensor:
        w = torch.ones(m.shape[-1], dtype=m.dtype, device=m.device)
        w[self.tokens] = self.scale
        return m * w


class Mirror:
    """Swap the maps of counterpart body parts (left/right legs, arms, or both)."""

    def __init__(self, part: str = "all"):
        if part not in sk.PART_MIRROR_PAIRS:
            raise ValueError(f"mirror part must be one of {', '.join(sk.PART_MIRROR_PAIRS)}, got {part!r}")
        perm = list(range(sk.BODY_PARTS.size))
        for a, b in sk.PART_MIRROR_PAIRS[part]:
            perm[a], perm[b] = b, a
        self.part = part
        self.perm = torch.tensor(perm)

    def __call__(self, m: torch.Tensor) -> torch.Tensor:   # (b, heads, T, J, L)
        return m.index_select(3, self.perm.to(m.device))    # a new tensor: stored maps stay as they were

    def self_attention(self, kind: str, m: torch.Tensor, frames: int, parts: int) -> torch.Tensor:
        """The source's self-attention as its mirror image would have it: part p of the target
        takes part perm[p]'s temporal map, and skeletal maps are permuted on both axes.
        Injecting unmirrored maps would hold the edit to the source's sides."""
        perm = self.perm.to(m.device)
        if kind == "temporal":                              # (b * parts, heads, T, T)
            return m.unflatten(0, (-1, parts)).index_select(1, perm).flatten(0, 1)
        return m.index_select(2, perm).index_select(3, perm)  # skeletal: (b * frames, heads, J, J)


# ---------------------------------------------------------------- latent blending


class HoldParts:
    """Prompt-to-Prompt's local blending at the level of body parts: after every denoising step the
    edited branch takes the source branch's latents of the held parts, so those parts (and, with the
    root part, the root's path) do what they do in the source while the attention edit changes the rest.
    The maps cannot choose the parts themselves: a manner word attends to every part alike."""

    def __init__(self, parts: str, source: int = 0, target: int = 1):
        if parts not in sk.PART_GROUPS:
            raise ValueError(f"held parts must be one of {', '.join(sk.PART_GROUPS)}, got {parts!r}")
        self.parts, self.source, self.target = parts, source, target
        self.index = torch.tensor(sk.PART_GROUPS[parts])

    def __call__(self, x: torch.Tensor) -> torch.Tensor:     # latents (rows, T/4, parts, D)
        idx = self.index.to(x.device)
        out = x.clone()
        out[self.target, :, idx] = x[self.source, :, idx]
        return out

    def replayed(self, run) -> Callable[[torch.Tensor], torch.Tensor]:
        """The blend for an edit whose source is a recorded run (salad.editing.replay): the edited
        branch, the only row, takes the held parts of the run's latents after the same step."""
        taken = iter(run.latents)

        def blend(x: torch.Tensor) -> torch.Tensor:
            idx = self.index.to(x.device)
            out = x.clone()
            out[:, :, idx] = next(taken).to(x)[:, :, idx]
            return out
        return blend


# ---------------------------------------------------------------- the controller


class AttentionEdit(RowAddressed):
    """Algorithm 1: the target branch's cross-attention becomes Edit(M_source, M_target, t),
    and its temporal and skeletal self-attention follow the source for the first
    `self_inject` share of the steps. Values always come from the target branch's own
    prompt and hidden states, as in the paper. `observers` see the maps actually used.
    replay: a recorded source run (salad.editing.replay) whose maps stand in for the source rows,
    which the forward then lacks (rows.source is None).
    """

    def __init__(self, rows: Rows, steps: int, rule, transforms=(), self_inject: float = DEFAULT_SELF_INJECT,
                 observers=(), replay=None):
        if not 0.0 <= self_inject <= 1.0:
            raise ValueError(f"self-attention injection must be a fraction in [0, 1], got {self_inject}")
        if (rows.source is None) != (replay is not None):
            raise ValueError("the source's maps come from source rows or from a replayed run, one of the two")
        self.rows, self.rule, self.transforms = rows, rule, list(transforms)
        self.self_inject = self_inject
        self.counter = StepCounter(steps)
        self.observers = list(observers)
        self.replay = replay
        self._counted = False

    def wants(self, kind: str, layer: int) -> bool:
        """Asked before every attention call of the forward, so the step is counted here. A replayed edit's
        self-attention has nothing to read or change once the injection is over (no source rows, no
        recorder): those calls run fused, a tenth of the forward's time."""
        self.counter.tick(kind, layer)
        self._counted = True
        return self.replay is None or kind == CROSS or self.counter.fraction < self.self_inject

    def _source(self, call: AttentionCall) -> torch.Tensor:
        if self.replay is not None:
            return self.replay.probs(self.counter.step, call)
        return call.probs[call_rows(call, self.at(self.rows.source))]

    def __call__(self, call: AttentionCall) -> torch.Tensor:
        if not self._counted:           # called directly rather than by an attention module
            self.counter.see(call)
        self._counted = False
        probs = call.probs
        if call.kind == CROSS:
            probs = self._cross(call)
        elif self.counter.fraction < self.self_inject:
            injected = self._source(call)
            for t in self.transforms:
                if hasattr(t, "self_attention"):
                    injected = t.self_attention(call.kind, injected, call.frames, call.parts)
            probs = probs.clone()
            probs[call_rows(call, self.at(self.rows.target))] = injected
        for obs in self.observers:
            obs(AttentionCall(call.kind, call.layer, probs, call.batch, call.frames, call.parts))
        return probs

    def _cross(self, call: AttentionCall) -> torch.Tensor:
        N, H, Q, L = call.probs.shape
        src = self._source(call).view(-1, H, call.frames, call.parts, L)
        tgt = call.probs.view(N, H, call.frames, call.parts, L)[self.at(self.rows.target)]
        edited = self.rule(src, tgt, self.counter.fraction)
        for t in self.transforms:
            edited = t(edited)
        out = call.probs.clone()
        out[self.at(self.rows.target)] = edited.reshape(-1, H, Q, L).to(out.dtype)
        return out

    def own_lowest_row(self) -> int:
        return min(r.start for r in (self.rows.source, self.rows.target) if r is not None)
