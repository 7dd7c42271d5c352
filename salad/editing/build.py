"""Assembling an attention edit from its EditSpec.

Both plain editing (Pipeline.edit) and editing under guided control (Pipeline.control
with edit=...) run the same controller on a four-row batch

    ["", "", source prompt, target prompt]   (CFG layout of controllers.cfg_rows(1))

or, for the consistency student (guidance is its input, not a second batch half), on the
two rows [source prompt, target prompt], so the choice of rule, the word look-ups for
re-weighting and the attention store are built here once. An edit whose source branch was
recorded (salad.editing.replay) runs the edited branch's rows ["", target prompt] alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from ..models.text import TextFeatures
from .align import align_tokens
from .controllers import AttentionEdit, HoldParts, KeepSource, Mirror, Refine, Reweight, Rows, WordSwap, cfg_rows
from .spec import DEFAULT_TAU, EditSpec
from .replay import SourceRecorder, SourceRun
from .store import AttentionMaps, AttentionStore


@dataclass
class EditPlan:
    controller: AttentionEdit
    store: AttentionStore
    text: TextFeatures          # the rows the forward runs
    params: dict = field(default_factory=dict)
    # latent blending after each step (rows: source 0, edited 1 of the sampler's latent batch, or the
    # edited branch alone where the source is replayed); None: none
    blend: Callable[[torch.Tensor], torch.Tensor] | None = None
    replay: SourceRun | None = None
    recorder: SourceRecorder | None = None      # records the source branch, to be replayed later

    def maps(self, source_frames: int, edited_frames: int) -> tuple[AttentionMaps, AttentionMaps]:
        """The source's and the edited motion's word-level cross-attention."""
        if self.replay is not None:
            return self.replay.maps_at(source_frames), self.store.maps(0, edited_frames)
        return self.store.maps(0, source_frames), self.store.maps(1, edited_frames)


def build_edit(text, steps: int, frames: int, spec: EditSpec, source_prompt: str, target_prompt: str,
               cfg_layout: bool = True, hold: str | None = None, replay: SourceRun | None = None,
               record: bool = False) -> EditPlan:
    """The controller (with an attention store on the two conditional rows) of `spec` for encoded
    `text` = ["", "", source_prompt, target_prompt] (cfg_layout) or [source_prompt, target_prompt]
    and `steps` denoising steps; the prompts are the cleaned ones (Pipeline.check_edit) and `hold`
    the parts held to the source, "auto" resolved (Pipeline.resolve_hold). replay: the source branch's
    recorded run (cfg_layout only); the plan's forward then runs text's rows 1 and 3 alone. record: the
    plan's recorder records the source branch as it runs (cfg_layout, without replay)."""
    rows = cfg_rows(1) if cfg_layout else Rows(source=slice(0, 1), target=slice(1, 2))
    src_row, tgt_row = rows.source.start, rows.target.start
    if replay is not None:
        if not cfg_layout:
            raise ValueError("only an edit in the CFG layout (the teacher's samplers) replays a recorded source")
        if replay.held_frames is not None:
            raise ValueError("this recorded source run stopped early (its length left the band): nothing to replay")
    if record and (replay is not None or not cfg_layout):
        raise ValueError("only a source branch that runs in the CFG layout is recorded")
    mode = spec.mode
    align_mode = {"swap": "swap", "refine": "refine"}.get(mode, "same" if target_prompt == source_prompt else "refine")
    alignment = align_tokens(text, source_row=src_row, target_row=tgt_row, mode=align_mode)
    if mode == "swap":
        tau = DEFAULT_TAU["swap"] if spec.tau is None else spec.tau
        source_led = math.ceil((1.0 - tau) * steps - 1e-9)      # steps with step / steps < 1 - tau
        rule = WordSwap(alignment, tau, own_replaced=source_led <= 1)
    elif mode == "refine" or target_prompt != source_prompt:
        rule = Refine(alignment, DEFAULT_TAU["refine"] if spec.tau is None else spec.tau)
    else:
        rule = KeepSource()
    transforms = []
    words = [w.lower() for w in text.words[tgt_row]]
    for word, scale in spec.reweight:
        if word.lower() not in words:
            raise ValueError(f"cannot re-weight {word!r}: it is not a word of {target_prompt!r} ({', '.join(words)})")
        transforms.append(Reweight(text.token_indices(tgt_row, words.index(word.lower())), scale))
    if spec.mirror is not None:
        transforms.append(Mirror(spec.mirror))
    params = spec.params(getattr(rule, "tau", None), hold)
    held = None if hold is None else HoldParts(hold)
    if replay is not None:
        text = text.select([1, 3])             # cfg_rows(1)'s edited branch: ["", target prompt]
        store = AttentionStore(text, rows=slice(1, 2), frames=frames)
        controller = AttentionEdit(Rows(source=None, target=slice(1, 2)), steps, rule, transforms,
                                   self_inject=spec.self_inject, observers=[store], replay=replay)
        return EditPlan(controller, store, text, params, None if held is None else held.replayed(replay), replay)
    store = AttentionStore(text, rows=slice(src_row, tgt_row + 1), frames=frames)
    recorder = SourceRecorder(rows.source) if record else None
    controller = AttentionEdit(rows, steps, rule, transforms, self_inject=spec.self_inject,
                               observers=[store] + ([recorder] if recorder else []))
    return EditPlan(controller, store, text, params, held, recorder=recorder)


def step_follower(controller: AttentionEdit) -> Callable[[int], None]:
    """A hook for guided_sample's before_model: keeps the controller's step count on the
    denoising step when time travel runs the network several times per step."""
    counter = controller.counter

    def before_model(i: int) -> None:
        counter.step = i - 1        # the first attention call of the forward advances it to i
    return before_model
