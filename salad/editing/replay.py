"""A source branch sampled once and replayed in later edits of it.

An edit's source branch is the source prompt sampled from the edit's seed: the same computation
as generating that prompt, and the same in every edit of it. Recorded once (every attention map
of its conditional row at every step, and its latents after each step), it lets an edit run the
edited branch alone, two rows of the batched forward instead of four, with the source's maps and
latents read back where AttentionEdit and HoldParts would take them from the source rows.
A teacher recording of a 9.8 s canvas at 50 steps holds about 90 MB (float32), so few are kept.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Hashable

import torch
import torch.nn.functional as F

from ..models.attention import CROSS, AttentionCall
from .store import AttentionMaps, RowAddressed, StepCounter, call_rows


@dataclass
class SourceRun:
    """One sampling of a source prompt: maps[(step, kind, layer)] are the probabilities its conditional
    row's attention used (cross: (1, heads, T'*J, L); temporal: (J, heads, T', T'); skeletal: (T', heads,
    J, J)), latents[i] its latents after step i + 1, attention its word-level cross-attention. An auto-length
    run stopped because its length left `band` records that instead: held_frames, the length to sample at."""

    maps: dict[tuple[int, str, int], torch.Tensor] = field(default_factory=dict)
    latents: list[torch.Tensor] = field(default_factory=list)
    attention: AttentionMaps | None = None
    held_frames: int | None = None
    band: tuple[int, int] | None = None

    def probs(self, step: int, call: AttentionCall) -> torch.Tensor:
        """The recorded maps standing in for the source row's in `call` (an edited-branch forward). A cross
        map's token axis is the padded length of the batch it was recorded in, which the source prompt never
        exceeds: it is cut or zero-padded to the call's (the source's padding attends to nothing)."""
        m = self.maps[(step, call.kind, call.layer)].to(call.probs.device, call.probs.dtype)
        if call.kind == CROSS:
            tokens = call.probs.shape[-1]
            m = m[..., :tokens] if m.shape[-1] >= tokens else F.pad(m, (0, tokens - m.shape[-1]))
        return m

    def maps_at(self, frames: int) -> AttentionMaps | None:
        return None if self.attention is None else replace(self.attention, frames=frames)


class SourceRecorder(RowAddressed):
    """A controller that records (never changes) one motion's conditional row into a SourceRun, and
    passes every call on to `observers` (an attention store). Its step() is told each step's latents."""

    def __init__(self, row: slice, observers=()):
        self.row, self.observers = row, list(observers)
        self.counter = StepCounter()
        self.run = SourceRun()

    def __call__(self, call: AttentionCall) -> torch.Tensor:
        self.counter.see(call)
        self.run.maps[(self.counter.step, call.kind, call.layer)] = \
            call.probs[call_rows(call, self.at(self.row))].detach().clone()
        for obs in self.observers:
            obs(call)
        return call.probs

    def step(self, latents: torch.Tensor) -> None:
        """The recorded row's latents (1, T', J, D) after the step just taken."""
        self.run.latents.append(latents.detach().clone())

    def own_lowest_row(self) -> int:
        return self.row.start


class SourceRuns:
    """The last `capacity` recorded source runs, by the key of everything that decides them."""

    def __init__(self, capacity: int = 2):
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        self.capacity = capacity
        self._runs: OrderedDict[Hashable, SourceRun] = OrderedDict()

    def get(self, key: Hashable) -> SourceRun | None:
        run = self._runs.get(key)
        if run is not None:
            self._runs.move_to_end(key)
        return run

    def put(self, key: Hashable, run: SourceRun) -> None:
        if self.capacity == 0:
            return
        self._runs[key] = run
        self._runs.move_to_end(key)
        while len(self._runs) > self.capacity:
            self._runs.popitem(last=False)

    def clear(self) -> None:
        self._runs.clear()

    def __len__(self) -> int:
        return len(self._runs)
