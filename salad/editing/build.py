"""Assembling an attention edit from its user-facing arguments.

Both plain editing (Pipeline.edit) and editing under guided control (Pipeline.control
with edit=...) run the same controller on a four-row batch

    ["", "", source prompt, target prompt]   (CFG layout of controllers.cfg_rows(1))

so the choice of rule, the word look-ups for re-weighting and the attention store are
built here once.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from .align import align_tokens
from .controllers import AttentionEdit, KeepSource, Mirror, Refine, Reweight, WordSwap, cfg_rows
from .store import AttentionStore

EDIT_MODES = ("swap", "refine", "reweight", "mirror")
EDIT_KEYS = ("mode", "target", "tau", "reweight", "mirror", "self_inject")


@dataclass
class EditPlan:
    controller: AttentionEdit
    store: AttentionStore
    params: dict = field(default_factory=dict)


def edit_arguments(mode: str, source_prompt: str, target_prompt: str | None, reweight: dict | None,
                   mirror: str | None) -> tuple[str, str | None]:
    """Check the mode against its arguments; returns the target prompt (the source's when the
    mode keeps the prompt) and the mirrored part ("all" when mirroring without one).
    Prompts must already be cleaned by Pipeline.check_prompt."""
    if mode not in EDIT_MODES:
        raise ValueError(f"mode must be one of {', '.join(EDIT_MODES)}, got {mode!r}")
    if mode in ("swap", "refine") and target_prompt is None:
        raise ValueError(f"{mode} needs a target prompt")
    if target_prompt is None:
        target_prompt = source_prompt
    if mode == "reweight" and not reweight:
        raise ValueError("reweight needs words and scales, e.g. reweight={'high': 2.0}")
    if mode == "mirror" and mirror is None:
        mirror = "all"
    return target_prompt, mirror


def build_edit(text, steps: int, frames: int, mode: str, source_prompt: str, target_prompt: str,
               tau: float | None = None, reweight: dict[str, float] | None = None, mirror: str | None = None,
               self_inject: float = 0.2) -> EditPlan:
    """The controller (with an attention store on the two conditional rows) for encoded
    `text` = ["", "", source_prompt, target_prompt] and `steps` denoising steps."""
    rows = cfg_rows(1)
    align_mode = {"swap": "swap", "refine": "refine"}.get(mode, "same" if target_prompt == source_prompt else "refine")
    alignment = align_tokens(text, source_row=2, target_row=3, mode=align_mode)
    if mode == "swap":
        rule = WordSwap(alignment, 0.8 if tau is None else tau)
    elif mode == "refine" or target_prompt != source_prompt:
        rule = Refine(alignment, 0.0 if tau is None else tau)
    else:
        rule = KeepSource()
    transforms = []
    words = [w.lower() for w in text.words[3]]
    for word, scale in (reweight or {}).items():
        if word.lower() not in words:
            raise ValueError(f"cannot re-weight {word!r}: it is not a word of {target_prompt!r} ({', '.join(words)})")
        transforms.append(Reweight(text.token_indices(3, words.index(word.lower())), scale))
    if mirror is not None:
        transforms.append(Mirror(mirror))
    store = AttentionStore(text, rows=slice(2, 4), frames=frames)
    controller = AttentionEdit(rows, steps, rule, transforms, self_inject=self_inject, observers=[store])
    params = {"mode": mode, "tau": getattr(rule, "tau", None), "reweight": reweight, "mirror": mirror,
              "self_inject": self_inject}
    return EditPlan(controller, store, params)


def step_follower(controller: AttentionEdit) -> Callable[[int], None]:
    """A hook for guided_sample's before_model: keeps the controller's step count on the
    denoising step when time travel runs the network several times per step."""
    counter = controller.counter

    def before_model(i: int) -> None:
        counter.step = i - 1        # the first attention call of the forward advances it to i
    return before_model
