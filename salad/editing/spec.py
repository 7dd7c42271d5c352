"""What an attention edit is asked to do (EditSpec) and what it gives back (EditResult).

Every way into editing (Pipeline.edit, Pipeline.control(edit=...), real-motion editing, the
CLI, the studio) builds one EditSpec, so the defaults, the checks and the rule that mirroring
without a body part mirrors all of it live here only. Prompts are cleaned by the pipeline
(Pipeline.check_edit), which knows their limits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from numbers import Real
from typing import TYPE_CHECKING, Mapping

if TYPE_CHECKING:
    from ..motion.motion import Motion

EDIT_MODES = ("swap", "refine", "reweight", "mirror")
# The keys of salad.motion.skeleton.PART_MIRROR_PAIRS, spelled out so that this module (and the
# studio's settings) load without torch; tests keep the two equal.
MIRROR_PARTS = ("lower", "upper", "all")
# Body parts whose latents the edited branch takes from the source at every step (Prompt-to-Prompt's
# local blending, at the skeleton's part level): "lower" = root and legs, "upper" = spine, arms and head.
# "auto" holds the lower body when a re-weighting edit's prompt asks for an action done in place.
HOLD_PARTS = ("lower", "upper")
HOLD_CHOICES = ("auto",) + HOLD_PARTS
# Share of T during which the source's maps lead: swap's early steps fix the layout of the
# motion, refine keeps the aligned source maps throughout.
DEFAULT_TAU = {"swap": 0.8, "refine": 0.0}
DEFAULT_SELF_INJECT = 0.2
MAX_REWEIGHT = 3.0          # |s| beyond 3 turns the motion into noise


def _fraction(what: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value) or not 0 <= value <= 1:
        raise ValueError(f"{what} in [0, 1], got {value!r}")
    return float(value)


@dataclass(frozen=True)
class EditSpec:
    """One attention edit.

    mode: "swap" (target replaces words), "refine" (target adds words), "reweight" or "mirror";
    None picks it from what is given (a target: swap; else a mirror part: mirror; else
    re-weighted words: reweight).
    target: the edited prompt (swap, refine; optional with reweight and mirror, which then also
    refine towards it); None keeps the source prompt.
    tau: the source's maps lead while t >= tau * T; None is the rule's default (DEFAULT_TAU).
    reweight: {word of the edited prompt: scale in [-MAX_REWEIGHT, MAX_REWEIGHT]}, kept as pairs.
    mirror: "lower", "upper" or "all" (mirror mode without a part mirrors all).
    self_inject: share of the steps with the source's self-attention.
    hold: body parts that follow the source throughout ("lower", "upper"; None: none); "auto" holds
    "lower" in a re-weighting of an unchanged prompt whose action is done in place (Pipeline.resolve_hold).
    """

    mode: str | None = None
    target: str | None = None
    tau: float | None = None
    reweight: tuple[tuple[str, float], ...] = ()
    mirror: str | None = None
    self_inject: float = DEFAULT_SELF_INJECT
    hold: str | None = "auto"

    def __post_init__(self):
        weights = self.reweight
        if weights is None:
            weights = ()
        elif isinstance(weights, Mapping):
            weights = tuple(weights.items())
        elif isinstance(weights, (str, bytes)) or not hasattr(weights, "__iter__"):
            raise ValueError(f"reweight must be a dict of word: scale, got {self.reweight!r}")
        weights = tuple(tuple(pair) for pair in weights)
        for pair in weights:
            if len(pair) != 2 or not isinstance(pair[0], str) or isinstance(pair[1], bool) \
                    or not isinstance(pair[1], Real):
                raise ValueError(f"reweight must be a dict of word: scale, got {self.reweight!r}")
            if not math.isfinite(pair[1]) or not -MAX_REWEIGHT <= pair[1] <= MAX_REWEIGHT:
                raise ValueError(f"re-weighting scale must be in [-{MAX_REWEIGHT:g}, {MAX_REWEIGHT:g}], got {pair[1]}")
        object.__setattr__(self, "reweight", tuple((w, float(s)) for w, s in weights))

        mode = self.mode
        if mode is None:
            mode = ("swap" if self.target is not None else "mirror" if self.mirror else
                    "reweight" if weights else None)
            if mode is None:
                raise ValueError("edit needs a mode, a target prompt, a mirror part or re-weighted words")
        if mode not in EDIT_MODES:
            raise ValueError(f"mode must be one of {', '.join(EDIT_MODES)}, got {mode!r}")
        if self.target is not None and not isinstance(self.target, str):
            raise ValueError(f"the target prompt must be a string, got {type(self.target).__name__}")
        if mode in ("swap", "refine") and self.target is None:
            raise ValueError(f"{mode} needs a target prompt")
        if mode == "reweight" and not weights:
            raise ValueError("reweight needs words and scales, e.g. reweight={'high': 2.0}")
        mirror = self.mirror
        if mirror is None and mode == "mirror":
            mirror = "all"
        if mirror is not None and mirror not in MIRROR_PARTS:
            raise ValueError(f"mirror part must be one of {', '.join(MIRROR_PARTS)}, got {mirror!r}")
        if self.hold is not None and self.hold not in HOLD_CHOICES:
            raise ValueError(f"hold must be one of {', '.join(HOLD_CHOICES)} or None, got {self.hold!r}")
        object.__setattr__(self, "mode", mode)
        object.__setattr__(self, "mirror", mirror)
        if self.tau is not None:
            object.__setattr__(self, "tau", _fraction("tau must be", self.tau))
        object.__setattr__(self, "self_inject", _fraction("self-attention injection must be a fraction", self.self_inject))

    @classmethod
    def of(cls, edit) -> EditSpec:
        """An EditSpec as given, or one from a dict with the field names as keys (what
        Pipeline.control(edit=...) took before EditSpec existed)."""
        if isinstance(edit, cls):
            return edit
        if not isinstance(edit, Mapping):
            raise ValueError(f"edit must be an EditSpec or a dict such as {{'mode': 'mirror', 'mirror': 'upper'}}, "
                             f"got {type(edit).__name__}")
        keys = [f.name for f in fields(cls)]
        unknown = sorted(set(edit) - set(keys))
        if unknown:
            raise ValueError(f"unknown edit option(s) {', '.join(map(repr, unknown))}; use {', '.join(keys)}")
        return cls(**edit)

    @classmethod
    def from_arguments(cls, spec: EditSpec | None = None, **settings) -> EditSpec:
        """The edit of a call that takes either `spec` or the settings as keyword arguments
        (Pipeline.edit's mode=, tau=, ...); settings left at their defaults do not count."""
        if spec is None:
            return cls(**settings)
        defaults = {"mode": "swap", "self_inject": DEFAULT_SELF_INJECT, "hold": "auto"}
        given = sorted(k for k, v in settings.items() if v != defaults.get(k))
        if given:
            raise ValueError(f"give the edit either as an EditSpec or as keyword arguments, not both "
                             f"({', '.join(given)} given with spec)")
        return cls.of(spec)

    @property
    def weights(self) -> dict[str, float] | None:
        """The re-weighted words as a dict, None when there are none."""
        return dict(self.reweight) or None

    def target_prompt(self, source_prompt: str) -> str:
        """The edited branch's prompt."""
        return source_prompt if self.target is None else self.target

    def params(self, tau: float | None, hold: str | None) -> dict:
        """The settings as an EditResult records them (tau: the one the rule used; hold: the parts held)."""
        return {"mode": self.mode, "tau": tau, "reweight": self.weights, "mirror": self.mirror,
                "self_inject": self.self_inject, "hold": hold}


@dataclass
class EditResult:
    source: Motion
    edited: Motion
    source_attention: object = None
    edited_attention: object = None
    params: dict = field(default_factory=dict)
