"""The fixed prompt suite of the editing benchmark, worded in the caption templates' vocabulary
(salad.data.captions) so that the model has seen every phrase in training.

Each case names what the edited motion should be (classifier labels, optionally a physical sign), which
label of the source it should keep, and which motion its preservation is measured against:

* mirror: one-hand wave/raise prompts mirrored with mode="mirror" on all parts or on the arms only.
  Success: the classifier's side flips (left <-> right) and the other wrist now leads physically (travels
  further in a wave, rises higher in a raise). The baseline regenerates the prompt with left and right
  swapped. Preservation is measured against the mirrored source for "all"; for "upper" the legs should
  not move, so against the source itself with the lower body's pose.
* swap: content swaps with a physical signature (walk -> run must speed up, a left turn must turn right)
  or an upper-body one (wave -> raise keeps the legs), side swaps (the new hand must rise as high as when
  the target prompt is generated), and style swaps (normal -> exhausted, ...).
* refine: a style word appended to a plain prompt; the classifier must see the style and the physical
  read-outs move the way the style moves them in the real captures (exhausted: slower; energetic: faster,
  livelier hands; elderly: slower and more bent).
* reweight: a word of the prompt scaled by s. For an action word the amplitude of the acting hand (wrist
  travel for waves, wrist height for raises) should grow with s; for every word the root path and the
  lower body should stay within REWEIGHT_BOUNDS of the source.

There are two suites. "tuned" is the one the editing defaults (tau, self-attention injection) were
chosen on; "held-out" asks for the same kinds of edit in other words and was never used to tune anything.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..data.captions import swap_left_right

MODES = ("mirror", "swap", "refine", "reweight")
SUITES = ("tuned", "held-out")
DEFAULT_SCALES = (-2.0, -1.0, 0.0, 1.0, 2.0, 3.0)
# Directional checks against the source (reaches_target_height: against the regenerated target prompt).
PHYSICS = ("faster", "slower", "turn_left", "turn_right", "wrist_flip", "livelier", "leans_forward",
           "reaches_target_height")
TARGET_HEIGHT_SLACK = 0.10   # m: a swapped-in hand counts as raised when within this of the target's own height
# How far a re-weighted motion may leave its source, whatever s in [-2, 3]: mean root path distance and
# lower-body pose (m). Standing one-hand actions are the suite's re-weighting cases, so any walking away fails.
REWEIGHT_BOUNDS = {"root_dist_m": 0.30, "pose_mpjpe_m": 0.05}
AMPLITUDES = {"wrist_path": "{side}_wrist_path_m", "wrist_height": "{side}_wrist_height_m"}


@dataclass(frozen=True)
class EditCase:
    name: str
    mode: str                             # one of MODES
    group: str                            # summary row the case is counted in
    source: str
    target: str | None = None             # swap / refine target prompt
    seconds: float = 4.0
    expect: dict = field(default_factory=dict)          # head -> label of the edit; side "flip": the source's, mirrored
    source_expect: dict = field(default_factory=dict)   # what the source prompt asks for (a sanity check)
    physics: tuple[str, ...] = ()         # kinds of PHYSICS, all of which must hold
    keep: str | None = None               # classifier head whose label the edit should keep
    reference: str = "source"             # "source" or "mirrored": what preservation compares with
    pose_joints: str | None = None        # joint set whose pose should stay ("all", "lower", "upper")
    mirror: str | None = None             # mirror mode's part
    word: str | None = None               # reweight: the word to scale
    acting_side: str | None = None        # the hand whose amplitude is measured (reweight, livelier, target height)
    amplitude: str = "wrist_path"         # one of AMPLITUDES: the acting hand's measure (reweight, mirror)

    @property
    def baseline(self) -> str:
        """The prompt a plain regeneration gets: the target, the mirrored wording, or the prompt itself."""
        if self.mode in ("swap", "refine"):
            return self.target
        if self.mode == "mirror":
            return swap_left_right(self.source)
        return self.source

    def required_labels(self) -> dict[str, set[str]]:
        """Classifier classes this case needs, per head."""
        need: dict[str, set[str]] = {}
        for labels in (self.expect, self.source_expect):
            for head, label in labels.items():
                need.setdefault(head, set())
                if label != "flip":
                    need[head].add(label)
        if self.keep:
            need.setdefault(self.keep, set())
        if self.expect.get("side") == "flip":
            need["side"] |= {"left", "right"}
        return need


def _mirror_cases() -> list[EditCase]:
    out = []
    for part in ("all", "upper"):
        for verb, content in (("waves", "wave"), ("raises", "raise-up")):
            for side in ("left", "right"):
                out.append(EditCase(
                    name=f"{content}-{side} mirror-{part}", mode="mirror", group=f"mirror ({part})",
                    source=f"a person {verb} their {side} hand", mirror=part,
                    expect={"side": "flip"}, source_expect={"content": f"{content}-{side}-hand", "side": side},
                    physics=("wrist_flip",), keep="style",
                    amplitude="wrist_path" if verb == "waves" else "wrist_height",
                    reference="mirrored" if part == "all" else "source",
                    pose_joints="all" if part == "all" else "lower"))
    return out


def _swap_cases() -> list[EditCase]:
    c, d, s = "swap: content", "swap: side", "swap: style"
    return [
        EditCase("walk->run", "swap", c, "a person walks forward", "a person runs forward",
                 expect={"content": "run"}, source_expect={"content": "walk"}, physics=("faster",), keep="style"),
        EditCase("walk->run (active)", "swap", c, "a person walks forward energetically",
                 "a person runs forward energetically", expect={"content": "run"},
                 source_expect={"content": "walk", "style": "active"}, physics=("faster",), keep="style"),
        EditCase("turn-left->turn-right", "swap", c, "a person walks and turns left", "a person walks and turns right",
                 expect={"content": "walk-turn-right"}, source_expect={"content": "walk-turn-left"},
                 physics=("turn_right",), keep="style"),
        EditCase("wave->raise (right)", "swap", c, "a person waves their right hand",
                 "a person raises their right hand",
                 expect={"content": "raise-up-right-hand"}, source_expect={"content": "wave-right-hand"},
                 keep="style", pose_joints="lower"),
        EditCase("raise right->left", "swap", d, "a person raises their right hand", "a person raises their left hand",
                 expect={"content": "raise-up-left-hand", "side": "left"},
                 source_expect={"content": "raise-up-right-hand"}, physics=("reaches_target_height",),
                 acting_side="left", amplitude="wrist_height", keep="style", pose_joints="lower"),
        EditCase("wave left->right", "swap", d, "a person waves their left hand", "a person waves their right hand",
                 expect={"content": "wave-right-hand", "side": "right"}, source_expect={"content": "wave-left-hand"},
                 physics=("reaches_target_height",), acting_side="right", amplitude="wrist_height", keep="style",
                 pose_joints="lower"),
        EditCase("walk normal->exhausted", "swap", s, "a person walks forward normally",
                 "a person walks forward wearily", expect={"style": "exhausted"},
                 source_expect={"content": "walk", "style": "normal"}, physics=("slower",), keep="content"),
        EditCase("walk normal->active", "swap", s, "a person walks forward normally",
                 "a person walks forward energetically", expect={"style": "active"},
                 source_expect={"content": "walk", "style": "normal"}, physics=("faster",), keep="content"),
        EditCase("run normal->exhausted", "swap", s, "a person runs forward normally", "a person runs forward wearily",
                 expect={"style": "exhausted"}, source_expect={"content": "run", "style": "normal"},
                 physics=("slower",), keep="content"),
        EditCase("wave normal->exhausted", "swap", s, "a person waves their right hand normally",
                 "a person waves their right hand wearily", expect={"style": "exhausted"},
                 source_expect={"content": "wave-right-hand", "style": "normal"}, keep="content",
                 pose_joints="lower"),
    ]


def _refine_cases() -> list[EditCase]:
    g = "refine: style"
    return [
        EditCase("walk +wearily", "refine", g, "a person walks forward", "a person walks forward wearily",
                 expect={"style": "exhausted"}, source_expect={"content": "walk"}, physics=("slower",), keep="content"),
        EditCase("walk +in an exhausted way", "refine", g, "a person walks forward",
                 "a person walks forward in an exhausted way", expect={"style": "exhausted"},
                 source_expect={"content": "walk"}, physics=("slower",), keep="content"),
        EditCase("walk +energetically", "refine", g, "a person walks forward", "a person walks forward energetically",
                 expect={"style": "active"}, source_expect={"content": "walk"}, physics=("faster",), keep="content"),
        EditCase("run +wearily", "refine", g, "a person runs forward", "a person runs forward wearily",
                 expect={"style": "exhausted"}, source_expect={"content": "run"}, physics=("slower",), keep="content"),
        EditCase("wave +energetically", "refine", g, "a person waves their right hand",
                 "a person waves their right hand energetically", expect={"style": "active"},
                 source_expect={"content": "wave-right-hand"}, physics=("livelier",), acting_side="right",
                 keep="content", pose_joints="lower"),
    ]


def _reweight_cases() -> list[EditCase]:
    return [
        EditCase("waves (right)", "reweight", "reweight", "a person waves their right hand", word="waves",
                 acting_side="right", source_expect={"content": "wave-right-hand"}, pose_joints="lower"),
        EditCase("waves (left)", "reweight", "reweight", "a person waves their left hand", word="waves",
                 acting_side="left", source_expect={"content": "wave-left-hand"}, pose_joints="lower"),
        EditCase("raises (right)", "reweight", "reweight", "a person raises their right hand", word="raises",
                 acting_side="right", amplitude="wrist_height", source_expect={"content": "raise-up-right-hand"},
                 pose_joints="lower"),
    ]


def _held_out_cases() -> list[EditCase]:
    """Each kind of edit again, in wording the defaults were not tuned on (still the captions' vocabulary)."""
    return [
        EditCase("ho wave-left mirror-upper", "mirror", "mirror (upper)", "a woman waves the left arm",
                 mirror="upper", expect={"side": "flip"}, source_expect={"content": "wave-left-hand", "side": "left"},
                 physics=("wrist_flip",), keep="style", pose_joints="lower"),
        EditCase("ho raise-right mirror-all", "mirror", "mirror (all)", "a man raises the right arm", mirror="all",
                 expect={"side": "flip"}, source_expect={"content": "raise-up-right-hand", "side": "right"},
                 physics=("wrist_flip",), keep="style", amplitude="wrist_height", reference="mirrored",
                 pose_joints="all"),
        EditCase("ho jog->walk", "swap", "swap: content", "someone jogs straight ahead", "someone walks straight ahead",
                 expect={"content": "walk"}, source_expect={"content": "run"}, physics=("slower",), keep="style"),
        EditCase("ho turn-right->turn-left", "swap", "swap: content", "a man walks and turns right",
                 "a man walks and turns left", expect={"content": "walk-turn-left"},
                 source_expect={"content": "walk-turn-right"}, physics=("turn_left",), keep="style"),
        EditCase("ho wave->raise (left)", "swap", "swap: content", "a woman waves the left arm",
                 "a woman raises the left arm", expect={"content": "raise-up-left-hand"},
                 source_expect={"content": "wave-left-hand"}, keep="style", pose_joints="lower"),
        EditCase("ho raise left->right", "swap", "swap: side", "a woman raises the left arm",
                 "a woman raises the right arm", expect={"content": "raise-up-right-hand", "side": "right"},
                 source_expect={"content": "raise-up-left-hand"}, physics=("reaches_target_height",),
                 acting_side="right", amplitude="wrist_height", keep="style", pose_joints="lower"),
        EditCase("ho wave right->left", "swap", "swap: side", "a man waves the right arm", "a man waves the left arm",
                 expect={"content": "wave-left-hand", "side": "left"}, source_expect={"content": "wave-right-hand"},
                 physics=("reaches_target_height",), acting_side="left", amplitude="wrist_height", keep="style",
                 pose_joints="lower"),
        EditCase("ho walk casually->heavily", "swap", "swap: style", "a man walks straight ahead casually",
                 "a man walks straight ahead heavily", expect={"style": "exhausted"},
                 source_expect={"content": "walk"}, physics=("slower",), keep="content"),
        EditCase("ho jog normally->vigorously", "swap", "swap: style", "someone jogs along normally",
                 "someone jogs along vigorously", expect={"style": "active"}, source_expect={"content": "run"},
                 physics=("faster",), keep="content"),
        EditCase("ho stroll +like an elderly person", "refine", "refine: style", "a woman strolls along",
                 "a woman strolls along like an elderly person", expect={"style": "elderly"},
                 source_expect={"content": "walk"}, physics=("slower", "leans_forward"), keep="content"),
        EditCase("ho run +with no energy left", "refine", "refine: style", "a man runs straight on",
                 "a man runs straight on with no energy left", expect={"style": "exhausted"},
                 source_expect={"content": "run"}, physics=("slower",), keep="content"),
        EditCase("ho walk +full of energy", "refine", "refine: style", "someone walks straight ahead",
                 "someone walks straight ahead full of energy", expect={"style": "active"},
                 source_expect={"content": "walk"}, physics=("faster",), keep="content"),
        EditCase("ho wave +vigorously", "refine", "refine: style", "a woman waves the left arm",
                 "a woman waves the left arm vigorously", expect={"style": "active"},
                 source_expect={"content": "wave-left-hand"}, physics=("livelier",), acting_side="left",
                 keep="content", pose_joints="lower"),
        EditCase("ho waves (left)", "reweight", "reweight", "a woman waves the left arm", word="waves",
                 acting_side="left", source_expect={"content": "wave-left-hand"}, pose_joints="lower"),
        EditCase("ho raises (right)", "reweight", "reweight", "a man raises the right arm", word="raises",
                 acting_side="right", amplitude="wrist_height", source_expect={"content": "raise-up-right-hand"},
                 pose_joints="lower"),
        # a manner word scaled up must not turn a standing action into a walk
        EditCase("ho proudly (both raised)", "reweight", "reweight", "a person raises both hands proudly",
                 word="proudly", acting_side="right", amplitude="wrist_height",
                 source_expect={"content": "raise-up-both-hands"}, pose_joints="lower"),
    ]


def default_suite(modes=MODES, suite: str = "tuned") -> list[EditCase]:
    """The benchmark's cases of one suite for the given modes, in a fixed order."""
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise ValueError(f"unknown edit mode(s) {', '.join(map(repr, unknown))}; choose from {', '.join(MODES)}")
    if suite not in SUITES:
        raise ValueError(f"unknown edit suite {suite!r}; choose from {', '.join(SUITES)}")
    if suite == "held-out":
        cases = _held_out_cases()
    else:
        cases = _mirror_cases() + _swap_cases() + _refine_cases() + _reweight_cases()
    return [c for m in MODES if m in modes for c in cases if c.mode == m]
