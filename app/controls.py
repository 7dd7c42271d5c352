"""Control signals for the Control tab: preset pelvis paths, uploaded or example target
arrays, keyframes and the lower body taken from an earlier motion. Every signal is built
with salad.motion.control; this module only turns the tab's values into its arguments
and checks uploads (which come from anyone) before they are read."""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from salad.motion import skeleton as sk
from salad.motion.control import (
    ControlSignal, keyframe_signal, make_signal, preset_path, read_mola_control,
)
from salad.motion.representation import FPS

from .settings import MAX_UPLOAD_BYTES

PELVIS = sk.JOINT_NAMES.index("pelvis")
TASKS = {                                   # value -> label
    "path": "pelvis path (preset)",
    "mola": "control file (MoLA .npy, zeros = free)",
    "targets": "target array (.npy, NaN = free)",
    "inbetween": "in-betweening from my last motion",
    "upper": "upper-body edit of my last motion",
}
PRESETS = {                                 # value -> label; the shapes are salad.motion.control's
    "straight": "straight line",
    "circle": "circle (to the left)",
    "s-curve": "S-curve",
    "turn-left": "turn left",
    "turn-right": "turn right",
}
MAX_KEYFRAMES = 64
NPY_MAGIC = b"\x93NUMPY"


def preset_signal(preset: str, frames: int, speed_mps: float, fps: float) -> ControlSignal:
    """The pelvis following a preset path at a constant speed over `frames` frames."""
    # preset_path counts frames at the library's 20 fps; scaling the speed keeps the metres per frame.
    return preset_path(preset, frames, speed=float(speed_mps) * FPS / float(fps))


# ------------------------------------------------------------------ uploads

@dataclass(frozen=True)
class Upload:
    path: Path
    name: str          # the user's file name, made safe to show
    digest: str        # sha256 of the content: identical uploads are identical requests


def display_name(name) -> str:
    base = re.split(r"[\\/]", str(name or ""))[-1]
    safe = re.sub(r"[^A-Za-z0-9._ ()-]+", "_", base).strip()[:60]
    return safe or "the uploaded file"


def upload_file(value, root: Path, types: tuple[str, ...] = (".npy",),
                expected: str = "a NumPy .npy file") -> Upload | None:
    """The uploaded file a request refers to: a Gradio file value ({"path", "orig_name", ...})
    or a path, which must lie in the studio's upload cache `root` (any other server path is
    refused without saying whether it exists), with a name ending in one of `types` and a size
    within the limit. None when nothing was uploaded; the content is checked by its reader."""
    if value is None or value == "" or value == []:
        return None
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    if isinstance(value, dict):
        raw, name = value.get("path"), value.get("orig_name") or value.get("path")
    elif isinstance(value, str):
        raw, name = value, value
    else:
        raise ValueError(f"the upload must be one file, got {type(value).__name__}")
    if not isinstance(raw, str) or not raw:
        raise ValueError("the upload carries no file; upload it again")
    shown = display_name(name)
    try:
        path = Path(raw).resolve()
        path.relative_to(Path(root).resolve())
        ok = path.is_file()
    except (ValueError, OSError):
        ok = False
    if not ok:
        raise ValueError(f"{shown}: the upload was not found on the server; upload the file again")
    if not shown.lower().endswith(types):
        raise ValueError(f"{shown}: expected {expected}")
    size = path.stat().st_size
    if size > MAX_UPLOAD_BYTES:
        raise ValueError(f"{shown}: {size / 1e6:.1f} MB is more than the {MAX_UPLOAD_BYTES / 1e6:g} MB "
                         "an upload may have")
    if size == 0:
        raise ValueError(f"{shown}: the file is empty")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    return Upload(path, shown, digest)


def load_array(path: Path, name: str) -> np.ndarray:
    """A numeric array from an .npy file; pickled objects are never loaded."""
    with open(path, "rb") as f:
        if f.read(6) != NPY_MAGIC:
            raise ValueError(f"{name}: not a .npy array (the file lacks NumPy's header)")
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        pickled = "allow_pickle" in str(exc)
        reason = "it holds Python objects, which are not read" if pickled else "not a readable .npy array"
        raise ValueError(f"{name}: {reason}") from None
    if not isinstance(a, np.ndarray) or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name}: expected a numeric array, got dtype {getattr(a, 'dtype', type(a).__name__)}")
    return a


def _check_frames(name: str, frames: int, lo: int, hi: int, fps: float) -> None:
    if not lo <= frames <= hi:
        raise ValueError(f"{name}: {frames} frames; guided control needs {lo} to {hi} frames "
                         f"({lo / fps:g} to {hi / fps:g} s at {fps:g} fps)")


def mola_signal(path: Path, name: str, frames: tuple[int, int], fps: float) -> ControlSignal:
    """MoLA's format: (T, 22, 3) global positions in metres, all-zero joints free."""
    a = load_array(path, name)
    if a.ndim != 3 or a.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"{name}: expected shape (T, 22, 3) (MoLA's control format), got {a.shape}")
    _check_frames(name, a.shape[0], *frames, fps)
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or infinite values; MoLA's files mark free joints with zeros "
                         "(use 'target array' for NaN = free)")
    try:
        return read_mola_control(path)
    except ValueError as exc:        # its messages start with the server path; show the user's name
        raise ValueError(str(exc).replace(str(path), name)) from None


def target_signal(path: Path, name: str, frames: tuple[int, int], fps: float) -> ControlSignal:
    """(T, 22, 3) joint targets with NaN = free, or (T, 2) pelvis x, z per frame with NaN rows free."""
    a = load_array(path, name).astype(np.float64)
    if a.ndim == 2 and a.shape[1] == 2:
        targets = np.full((a.shape[0], sk.NUM_JOINTS, 3), np.nan)
        targets[:, PELVIS, 0], targets[:, PELVIS, 2] = a[:, 0], a[:, 1]
        a = targets
    elif a.ndim != 3 or a.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"{name}: expected shape (T, 22, 3) joint targets or (T, 2) pelvis x, z points, "
                         f"got {a.shape}")
    _check_frames(name, a.shape[0], *frames, fps)
    if np.isinf(a).any():
        raise ValueError(f"{name}: contains infinite values; mark free values with NaN")
    if np.isnan(a).all():
        raise ValueError(f"{name}: every value is NaN, so nothing is constrained")
    try:
        return make_signal(a)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


# ------------------------------------------------------------------ earlier motions

def parse_keyframes(spec, frames: int) -> tuple[int, ...]:
    """Keyframes as text ("first, last", "0, 20, 39", "0-3, 36-39") or a list of frame
    numbers (0-based) -> sorted unique frame indices within the motion."""
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        raise ValueError("give the keyframes to keep, e.g. 'first, last' or '0, 20, 39'")
    if isinstance(spec, (list, tuple)):
        items = [str(s) for s in spec]
    elif isinstance(spec, str):
        items = [s for s in re.split(r"[,;\s]+", spec.strip()) if s]
    else:
        raise ValueError(f"keyframes must be text such as 'first, last' or a list of frame numbers, got {spec!r}")
    named = {"first": 0, "start": 0, "last": frames - 1, "end": frames - 1}
    out: set[int] = set()
    for item in items:
        word = item.strip().lower()
        m = re.fullmatch(r"(\d+)\s*-\s*(\d+)", word)
        if word in named:
            chosen = [named[word]]
        elif word.isdigit():
            chosen = [int(word)]
        elif m:
            a, b = int(m.group(1)), int(m.group(2))
            if a > b:
                raise ValueError(f"keyframe range {item!r} runs backwards")
            chosen = list(range(a, b + 1))
        else:
            raise ValueError(f"keyframe {item!r} is not a frame number, a range like 0-3, 'first' or 'last'")
        bad = [f for f in chosen if not 0 <= f < frames]
        if bad:
            raise ValueError(f"keyframe {bad[0]} is outside the last motion's frames 0..{frames - 1}")
        out.update(chosen)
    if len(out) > MAX_KEYFRAMES:
        raise ValueError(f"{len(out)} keyframes; at most {MAX_KEYFRAMES} can be kept")
    return tuple(sorted(out))


def inbetween_signal(joints: np.ndarray, keyframes: tuple[int, ...]) -> ControlSignal:
    """Whole-body poses of `joints` kept at `keyframes`, everything between free."""
    return keyframe_signal({f: joints[f] for f in keyframes}, len(joints))


# ------------------------------------------------------------------ drawing

def pelvis_path(signal: ControlSignal, frames: int | None = None) -> np.ndarray | None:
    """(N, 3) floor-level points of the pelvis targets when the signal is a path (the pelvis
    x and z constrained on at least a quarter of the frames), else None."""
    n = signal.frames if frames is None else min(frames, signal.frames)
    on = signal.mask[:n, PELVIS, 0] & signal.mask[:n, PELVIS, 2]
    if on.sum() < max(2, n // 4):
        return None
    p = signal.targets[:n][on, PELVIS].astype(np.float64)
    p[:, 1] = 0.0
    return p


def list_examples(folder: Path | None) -> list[str]:
    """File names of the .npy control examples in `folder` (none without a folder)."""
    if folder is None or not Path(folder).is_dir():
        return []
    return sorted(p.name for p in Path(folder).glob("*.npy") if p.is_file())
