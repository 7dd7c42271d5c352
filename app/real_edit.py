"""Editing real motions in the studio: an uploaded BVH / NPY file or a test clip of a dataset
build, inverted and edited by text through `Pipeline.edit_real`, then saved and rendered next to
the input and its reconstruction. Uploads come from anyone: they are checked before they are read."""
from __future__ import annotations

import logging
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from salad.motion import representation as rep
from salad.motion import skeleton as sk
from salad.pipeline import MIN_AUTO_FRAMES

from .compare import Difference, motion_difference
from .controls import Upload, display_name, load_array, upload_file
from .session import Result, Session
from .settings import MAX_CLIPS, REAL_UPLOAD_TYPES
from .studio import Progress, Studio, file_writer, quiet, save_motion, slug
from .validation import RealEditRequest

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
        from salad.motion.bvh import BvhError, load_bvh

        try:
            joints = load_bvh(path, fps=rep.FPS).joints
        except (BvhError, ValueError) as exc:      # the reader's messages start with the server path
            reason = str(exc).replace(f"{path}: ", "").replace(str(path), name)
            raise ValueError(f"{name}: not a readable BVH file ({reason})") from None
        if not np.isfinite(joints).all():
            raise ValueError(f"{name}: the BVH file gives NaN or infinite joint positions")
        _check_length(name, len(joints), MIN_AUTO_FRAMES + 1)
        return RealInput(name, "bvh", joints, joints)
    arr = load_array(path, name).astype(np.float32)
    if arr.ndim == 3 and arr.shape[1:] == (sk.NUM_JOINTS, 3):
        kind, shown = "joints", arr
        _check_length(name, len(arr), MIN_AUTO_FRAMES + 1)
    elif arr.ndim == 2 and arr.shape[1] == 263:
        kind = "features"
        _check_length(name, len(arr), MIN_AUTO_FRAMES)
    else:
        raise ValueError(f"{name}: expected joints (T, 22, 3) in metres or HumanML3D features (T, 263), "
                         f"got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    if kind == "features":
        shown = rep.features_to_joints(arr).astype(np.float32)
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
        from salad.data.dataset import read_captions, read_split

        self.root = Path(root)
        names = read_split(self.root, "test")
        if (self.root / "labels.json").is_file():
            from salad.data.labels import read_labels
            from salad.eval.real_edit_bench import pick_test_clips

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
        from salad.eval.real_edit_bench import read_clip

        clip = self._clip(name)
        try:
            features, caption = read_clip(self.root, clip.name, max_frames)
        except (OSError, ValueError) as exc:
            log.error("reading clip %s failed: %s", clip.name, exc)
            raise ValueError(f"{clip.name}: the clip cannot be read from the dataset build") from None
        features = np.asarray(features, dtype=np.float32)
        if features.ndim != 2 or features.shape[1] != 263 or not np.isfinite(features).all():
            raise ValueError(f"{clip.name}: the dataset build holds no valid features for this clip")
        _check_length(clip.name, len(features), MIN_AUTO_FRAMES)
        return RealInput(clip.name, "clip", rep.features_to_joints(features).astype(np.float32), features, caption)


# ------------------------------------------------------------------ the edit

def reconstruction_error_m(result: Result) -> float:
    """A real edit's reconstruction error against its input (pelvis-aligned MPJPE, as the model saw it)."""
    return float(result.source.info["mpjpe_m"])


def edit_difference(result: Result) -> Difference:
    """Where a real edit changed the reconstruction."""
    return result.cached(("difference",), lambda: motion_difference(result.source.joints, result.motion.joints))


def _without_type(name: str) -> str:
    return re.sub(r"\.(bvh|npy)$", "", name, flags=re.IGNORECASE)


def file_stem(req: RealEditRequest) -> str:
    """The input's name and what was done to it, safe as a file name."""
    return f"{slug(_without_type(req.input_name), 32) or 'motion'}_{req.mode}"


def _stages(progress: Progress, steps: int):
    """edit_real reports (done, 2 * steps): the inversion first, then the edit."""
    def report(done: int, total: int) -> None:
        if done < steps:
            progress("inverting", done, steps)
        else:
            progress("editing", done - steps, steps)
    return report


def _input_label(name: str, limit: int = 32) -> str:
    stem = _without_type(name)
    return f"input: {stem if len(stem) <= limit else stem[:limit - 3] + '...'}"


def edit_real(studio: Studio, session: Session, req: RealEditRequest, motion: RealInput,
              progress: Progress = quiet) -> Result:
    """Invert and edit `motion` (under the model lock), save the edited motion (BVH, NPY joints
    and features) and render input, reconstruction and edit side by side."""
    from salad.render import render_side_by_side

    reused = session.reuse("real", req)
    if reused is not None:
        return reused
    folder = session.new_folder()
    try:
        res, timings = studio.sample_locked(req.steps, progress, lambda _report: studio.pipe.edit_real(
            motion.motion, req.source, req.target, mode=req.mode, steps=req.steps, cfg=req.cfg, tau=req.tau,
            reweight=dict(req.reweight) or None, mirror=req.mirror, self_inject=req.self_inject,
            inversion=req.inversion, trim=True, progress=_stages(progress, req.steps), foot_lock=req.foot_lock))
        timings.update(inversion_s=float(res.params["inversion_seconds"]), edit_s=float(res.params["edit_seconds"]))
        stem, edited = file_stem(req), res.edited
        saved = file_writer.submit(save_motion, edited, folder, f"{stem}_edited")
        # the input as it came, cut to the frames that were edited
        shown = motion.shown[:res.source.frames]
        labels = [_input_label(motion.name), "reconstruction", f"edited ({req.mode})"]
        mp4, timings["render_s"] = studio.rendered(progress, lambda report: render_side_by_side(
            [shown, res.source.joints, edited.joints], labels, folder / f"{stem}_side-by-side.mp4",
            fps=edited.fps, progress=report))
        files = {"mp4": mp4} | saved.result()
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    result = Result(req, res.edited, folder, files, timings, kind="real", source=res.source, given=motion,
                    params=res.params)
    session.add(result)
    return result
