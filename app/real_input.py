"""Motions to edit in the Real motion tab: an uploaded BVH / NPY file or a test clip of a dataset
build. Uploads come from anyone: they are checked before they are read."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from salad.data.dataset import read_captions, read_clip, read_split
from salad.data.labels import pick_test_clips, read_labels
from salad.motion import representation as rep
from salad.motion.bvh import BvhError, load_bvh
from salad.motion.real import input_kind, min_input_frames

from .controls import Upload, display_name, load_array, upload_file
from .settings import MAX_CLIPS, REAL_UPLOAD_TYPES

log = logging.getLogger("salad.studio")
CAPTION_CHARS = 90          # of a clip's caption in the picker


# ------------------------------------------------------------------ inputs

@dataclass(frozen=True)
class RealInput:
    """A motion to edit. `shown` is the input as it came, (T, 22, 3) joints at 20 fps, for the
    first panel; `motion` is what edit_real takes: joints (T, 22, 3) or raw features (T, 263)."""

    name: str           # the user's file name (made safe to show) or the clip's id
    kind: str           # bvh | joints | features | clip
    shown: np.ndarray
    motion: np.ndarray
    caption: str | None = None


def upload_path(value, root: Path) -> Upload | None:
    """The uploaded motion a request refers to (path, name to show, content digest), or None when
    nothing was uploaded; place, type and size are checked here, the content by read_upload."""
    return upload_file(value, root, REAL_UPLOAD_TYPES, "a BVH file (.bvh) or a NumPy array (.npy)")


def _check_length(name: str, frames: int, need: int) -> None:
    if frames < need:
        raise ValueError(f"{name}: {frames} frames ({frames / rep.FPS:.2f} s at {rep.FPS:g} fps) is too short; "
                         f"a motion needs at least {need} frames ({need / rep.FPS:.2f} s)")


def read_upload(path: Path, name: str) -> RealInput:
    """An uploaded .bvh (any skeleton the project's BVH reader maps onto the 22 joints) or .npy
    (joints (T, 22, 3) in metres, or raw features (T, 263)), checked for shape, values and length.
    Messages name the file as the user called it, never the server path."""
    if name.lower().endswith(".bvh"):
        try:
            joints = load_bvh(path, fps=rep.FPS).joints
        except (BvhError, ValueError) as exc:      # the reader's messages start with the server path
            reason = str(exc).replace(f"{path}: ", "").replace(str(path), name)
            raise ValueError(f"{name}: not a readable BVH file ({reason})") from None
        if not np.isfinite(joints).all():
            raise ValueError(f"{name}: the BVH file gives NaN or infinite joint positions")
        _check_length(name, len(joints), min_input_frames("joints"))
        return RealInput(name, "bvh", joints, joints)
    arr = load_array(path, name).astype(np.float32)
    kind = input_kind(arr)
    if kind is None:
        raise ValueError(f"{name}: expected joints (T, 22, 3) in metres or HumanML3D features (T, 263), "
                         f"got shape {arr.shape}")
    _check_length(name, len(arr), min_input_frames(kind))
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    shown = arr if kind == "joints" else rep.features_to_joints(arr).astype(np.float32)
    return RealInput(name, kind, shown, arr)


# ------------------------------------------------------------------ test clips

@dataclass(frozen=True)
class Clip:
    name: str
    caption: str


class ClipLibrary:
    """Test clips of a dataset build (HumanML3D layout): up to `limit` of them, spread evenly
    over the test split (over the labelled test clips when the build has labels.json)."""

    def __init__(self, root: str | Path, limit: int = MAX_CLIPS):
        self.root = Path(root)
        names = read_split(self.root, "test")
        if (self.root / "labels.json").is_file():
            listed = set(names)
            labels = {k: v for k, v in read_labels(self.root).items() if k in listed}
            names = pick_test_clips(labels, limit) if labels else []
        else:
            names = sorted(names)
            if len(names) > limit:
                names = [names[int(i)] for i in np.linspace(0, len(names) - 1, limit).round()]
        clips = []
        for name in names:
            texts = self.root / "texts" / f"{name}.txt"
            if not (self.root / "new_joint_vecs" / f"{name}.npy").is_file() or not texts.is_file():
                log.warning("%s: clip %s lacks its features or captions; not offered", self.root, name)
                continue
            captions = read_captions(texts)
            if captions:
                clips.append(Clip(name, captions[0].text))
        self.clips: dict[str, Clip] = {c.name: c for c in clips}

    def __len__(self) -> int:
        return len(self.clips)

    def choices(self) -> list[tuple[str, str]]:
        """Dropdown choices (clip id and its first caption, clip id)."""
        def label(c: Clip) -> str:
            text = c.caption if len(c.caption) <= CAPTION_CHARS else c.caption[:CAPTION_CHARS - 1] + "…"
            return f"{c.name}: {text}"
        return [(label(c), c.name) for c in self.clips.values()]

    def caption(self, name) -> str:
        return self._clip(name).caption

    def _clip(self, name) -> Clip:
        if not isinstance(name, str) or name not in self.clips:
            shown = display_name(name) if isinstance(name, str) else repr(name)
            raise ValueError(f"“{shown}” is not one of the offered test clips")
        return self.clips[name]

    def read(self, name, max_frames: int) -> RealInput:
        """A clip's raw features (its first max_frames) as an input to edit."""
        clip = self._clip(name)
        try:
            features, caption = read_clip(self.root, clip.name, max_frames)
        except (OSError, ValueError) as exc:
            log.error("reading clip %s failed: %s", clip.name, exc)
            raise ValueError(f"{clip.name}: the clip cannot be read from the dataset build") from None
        features = np.asarray(features, dtype=np.float32)
        if input_kind(features) != "features" or not np.isfinite(features).all():
            raise ValueError(f"{clip.name}: the dataset build holds no valid features for this clip")
        _check_length(clip.name, len(features), min_input_frames("features"))
        return RealInput(clip.name, "clip", rep.features_to_joints(features).astype(np.float32), features, caption)
