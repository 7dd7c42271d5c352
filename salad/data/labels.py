"""Per-motion labels of a labelled build (labels.json): content, style and the side an action refers to."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .captions import CONTENT_PHRASES, MIRRORED_CONTENT, STYLE_PHRASES

CONTENTS: tuple[str, ...] = tuple(sorted(CONTENT_PHRASES))
STYLES: tuple[str, ...] = tuple(sorted(STYLE_PHRASES))
SIDES: tuple[str, ...] = ("none", "left", "right", "both")

# The side each content refers to, in the unmirrored recording (see salad.data.captions for what each
# label does: "bye" and "guide" use the right hand, "respond" the left, "call" and "byebye" both).
_CONTENT_SIDE = {
    "wave-left-hand": "left", "raise-up-left-hand": "left", "walk-turn-left": "left", "walk-left": "left",
    "respond": "left",
    "wave-right-hand": "right", "raise-up-right-hand": "right", "walk-turn-right": "right", "walk-right": "right",
    "bye": "right", "guide": "right",
    "wave-both-hands": "both", "raise-up-both-hands": "both", "byebye": "both", "call": "both",
}
_FLIP = {"left": "right", "right": "left"}


def side_of(content: str, mirrored: bool) -> str:
    """Side of the body or turn direction a motion's action refers to.

    Mirrored copies of sided contents with a mirror label (e.g. wave-left-hand) already carry the swapped
    label; those without one ("bye", "guide", "respond") keep their label, so their side flips here.
    """
    if content not in CONTENT_PHRASES:
        raise KeyError(f"unknown content label {content!r}")
    side = _CONTENT_SIDE.get(content, "none")
    if mirrored and content not in MIRRORED_CONTENT:
        side = _FLIP.get(side, side)
    return side


@dataclass(frozen=True)
class MotionLabels:
    content: str
    style: str
    side: str
    mirrored: bool
    split: str


def read_labels(root: str | Path) -> dict[str, MotionLabels]:
    """labels.json of a dataset directory -> {motion id: labels}; checks every label is known."""
    path = Path(root) / "labels.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no labels.json (content/style labels are needed here)")
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: corrupt JSON ({e})") from None
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected an object of motion id -> labels")
    out = {}
    for name, entry in raw.items():
        try:
            content, style = entry["content"], entry["style"]
            mirrored = bool(entry.get("mirrored", False))
        except (KeyError, TypeError):
            raise ValueError(f"{path}: motion {name!r} lacks content/style labels") from None
        if content not in CONTENT_PHRASES:
            raise ValueError(f"{path}: motion {name!r} has unknown content {content!r}")
        if style not in STYLE_PHRASES:
            raise ValueError(f"{path}: motion {name!r} has unknown style {style!r}")
        out[name] = MotionLabels(content, style, side_of(content, mirrored), mirrored, str(entry.get("split", "")))
    return out


def content_of(root: str | Path, names: list[str]) -> list[str]:
    """The content class of each motion `names` (a sub-clip "id@start" takes its motion's), from root's
    labels.json; FileNotFoundError without one, ValueError where a motion has no labels."""
    labels = read_labels(root)
    content = []
    for name in names:
        lab = labels.get(name.split("@")[0])
        if lab is None:
            raise ValueError(f"{Path(root) / 'labels.json'}: no labels for motion {name!r}")
        content.append(lab.content)
    return content


def pick_test_clips(labels: dict, n: int, content: str | None = None, style: str | None = None) -> list[str]:
    """n test clips spread evenly over the sorted ids that match content/style."""
    names = sorted(k for k, v in labels.items() if v.split == "test" and (content is None or v.content == content)
                   and (style is None or v.style == style))
    if not names:
        raise ValueError(f"no test clips with content={content!r} style={style!r}")
    if n >= len(names):
        return names
    return [names[int(i)] for i in np.linspace(0, len(names) - 1, n).round()]
