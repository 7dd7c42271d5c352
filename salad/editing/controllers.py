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

from contextlib import ExitStack, contextmanager
from dataclasses import dataclass

import torch

from ..models.attention import CROSS, AttentionCall
from ..motion import skeleton as sk
from .align import TokenAlignment
from .spec import DEFAULT_SELF_INJECT, DEFAULT_TAU
from .store import RowAddressed, StepCounter


@dataclass
class Rows:
    """Where the branches sit in the batched forward (each a slice of batch rows)."""

    source: slice
    target: slice


def cfg_rows(batch: int) -> Rows:
    """Rows of the conditional source and target branches in the CFG layout above."""
    return Rows(source=slice(2 * batch, 3 * batch), target=slice(3 * batch, 4 * batch))


def _expand(rows: slice, per_row: int) -> slice:
    return slice(rows.start * per_row, rows.stop * per_row)


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


# ---------------------------------------------------------------- the controller


class AttentionEdit(RowAddressed):
    """Algorithm 1: the target branch's cross-attention becomes Edit(M_source, M_target, t),
    and its temporal and skeletal self-attention follow the source for the first
    `self_inject` share of the steps. Values always come from the target branch's own
    prompt and hidden states, as in the paper. `observers` see the maps actually used.
    """

    def __init__(self, rows: Rows, steps: int, rule, transforms=(), self_inject: float = DEFAULT_SELF_INJECT,
                 observers=()):
        if not 0.0 <= self_inject <= 1.0:
            raise ValueError(f"self-attention injection must be a fraction in [0, 1], got {self_inject}")
        self.rows, self.rule, self.transforms = rows, rule, list(transforms)
        self.self_inject = self_inject
        self.counter = StepCounter(steps)
        self.observers = list(observers)

    def __call__(self, call: AttentionCall) -> torch.Tensor:
        self.counter.see(call)
        probs = call.probs
        if call.kind == CROSS:
            probs = self._cross(call)
        elif self.counter.fraction < self.self_inject:
            per = call.parts if call.kind == "temporal" else call.frames
            src, tgt = _expand(self.at(self.rows.source), per), _expand(self.at(self.rows.target), per)
            injected = probs[src]
            for t in self.transforms:
                if hasattr(t, "self_attention"):
                    injected = t.self_attention(call.kind, injected, call.frames, call.parts)
            probs = probs.clone()
            probs[tgt] = injected
        for obs in self.observers:
            obs(AttentionCall(call.kind, call.layer, probs, call.batch, call.frames, call.parts))
        return probs

    def _cross(self, call: AttentionCall) -> torch.Tensor:
        N, H, Q, L = call.probs.shape
        grid = call.probs.view(N, H, call.frames, call.parts, L)
        src, tgt = grid[self.at(self.rows.source)], grid[self.at(self.rows.target)]
        edited = self.rule(src, tgt, self.counter.fraction)
        for t in self.transforms:
            edited = t(edited)
        out = call.probs.clone()
        out[self.at(self.rows.target)] = edited.reshape(-1, H, Q, L).to(out.dtype)
        return out

    def lowest_row(self) -> int:
        return min(self.rows.source.start, self.rows.target.start,
                   *(o.lowest_row() for o in self.observers if isinstance(o, RowAddressed)))

    @contextmanager
    def leading_rows_dropped(self, n: int):
        with ExitStack() as stack:
            stack.enter_context(super().leading_rows_dropped(n))
            for o in self.observers:
                if isinstance(o, RowAddressed):
                    stack.enter_context(o.leading_rows_dropped(n))
            yield
