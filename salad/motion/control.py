"""Control targets for guided generation: global joint positions plus an explicit mask.

Targets are (T, 22, 3) metres in the frame generated motions live in (Y up, starting
at the origin, facing +Z); the mask says which joint coordinates are constrained,
(T, 22) per joint or (T, 22, 3) per coordinate. Nothing is inferred from zeros except
when reading MoLA's files, whose convention it is.

Also here: the readers for control files (MoLA .npy, explicit targets, keyframes, a
saved motion's lower body), preset pelvis paths, and the error of a motion against a
signal, shared by the command line, the studio and the benchmark.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import skeleton as sk
from .representation import FPS, canonicalize


@dataclass
class ControlSignal:
    targets: np.ndarray     # (T, 22, 3) float32
    mask: np.ndarray        # (T, 22, 3) bool

    @property
    def frames(self) -> int:
        return self.targets.shape[0]

    def joint_mask(self) -> np.ndarray:
        """(T, 22): joints with any constrained coordinate."""
        return self.mask.any(-1)


def make_signal(targets, mask=None) -> ControlSignal:
    """Validate and normalise targets and mask. Without a mask, finite targets are constrained
    and NaN ones free (an infinite one is an error: a free entry is NaN)."""
    t = np.asarray(targets, dtype=np.float64)
    if t.ndim != 3 or t.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"targets must have shape (T, 22, 3), got {t.shape}")
    if mask is None:
        if np.isinf(t).any():
            raise ValueError("targets hold infinite values: give NaN for the entries that are free")
        m = np.isfinite(t)
    else:
        m = np.asarray(mask)
        if m.dtype != bool:
            raise ValueError(f"mask must be boolean, got dtype {m.dtype}")
        if m.shape == t.shape[:2]:
            m = np.repeat(m[..., None], 3, axis=-1)
        elif m.shape != t.shape:
            raise ValueError(f"mask must have shape (T, 22) or (T, 22, 3) matching targets {t.shape}, got {m.shape}")
    if not np.isfinite(t[m]).all():
        raise ValueError("constrained targets must be finite numbers")
    if not m.any():
        raise ValueError("the mask constrains nothing")
    if np.abs(t[m]).max() > 100:
        raise ValueError("targets are in metres; values over 100 m look like centimetres or garbage")
    return ControlSignal(np.where(m, t, 0.0).astype(np.float32), m.copy())


def control_errors(joints, signal: ControlSignal) -> np.ndarray:
    """Distances (m) between `joints` (T', 22, 3) and the targets at every constrained
    joint-frame of the first min(T', T) frames, frame-major. Only constrained coordinates
    count: a path that leaves the height free is scored in the ground plane."""
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"joints must have shape (T, 22, 3), got {j.shape}")
    n = min(len(j), signal.frames)
    m = signal.mask[:n]
    diff = np.where(m, j[:n] - signal.targets[:n], 0.0)
    return np.linalg.norm(diff, axis=-1)[m.any(-1)]


def crop_signal(signal: ControlSignal, frames: int) -> ControlSignal:
    """The first `frames` frames of a signal (which must still constrain something)."""
    if not 1 <= frames <= signal.frames:
        raise ValueError(f"cannot crop a {signal.frames}-frame control signal to {frames} frames")
    if not signal.mask[:frames].any():
        raise ValueError(f"the first {frames} frames of the control signal constrain nothing")
    return ControlSignal(signal.targets[:frames].copy(), signal.mask[:frames].copy())


# ---------------------------------------------------------------- files

def _unreadable(path: Path, e: Exception, what: str) -> ValueError:
    why = "it holds Python objects, which are never read" if "pickle" in str(e) else f"not a readable {what} ({e})"
    return ValueError(f"{path}: {why}")


def _load_npy(path: Path) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except (OSError, ValueError, EOFError) as e:
        raise _unreadable(path, e, ".npy array") from None
    if not isinstance(a, np.ndarray) or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{path}: expected a numeric array, got {getattr(a, 'dtype', type(a).__name__)}")
    return a


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except (OSError, ValueError, EOFError) as e:
        raise _unreadable(path, e, ".npz archive") from None


def _with_name(path: Path, build):
    """Run a signal builder, prefixing its validation errors with the file they came from."""
    try:
        return build()
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None


def _joints_shape(a: np.ndarray, path: Path, what: str = "joints") -> np.ndarray:
    if a.ndim != 3 or a.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"{path}: expected {what} of shape (T, 22, 3), got {a.shape}")
    return a


def read_mola_control(path: str | Path) -> ControlSignal:
    """MoLA's control .npy: (T, 22, 3) global positions, all-zero joints meaning "free".
    A joint is constrained when any of its coordinates is non-zero, so a target that
    happens to sit at x = 0 or z = 0 (the start of a path) stays constrained."""
    path = Path(path)
    a = _joints_shape(_load_npy(path), path, "MoLA control positions")
    if not np.isfinite(a).all():
        raise ValueError(f"{path}: contains NaN or infinite values; MoLA's files mark free joints with zeros")
    joint_mask = (a != 0).any(-1)
    return _with_name(path, lambda: make_signal(a, joint_mask))


def read_targets(path: str | Path) -> ControlSignal:
    """Explicit targets: an .npy (T, 22, 3) whose NaN entries are free, or an .npz with
    `targets` (T, 22, 3) and a boolean `mask` (T, 22) or (T, 22, 3)."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        z = _load_npz(path)
        if "targets" not in z:
            raise ValueError(f"{path}: an .npz control file needs a 'targets' array (and optionally 'mask'); "
                             f"it has {', '.join(sorted(z)) or 'nothing'}")
        t = _joints_shape(z["targets"], path, "targets")
        return _with_name(path, lambda: make_signal(t, z.get("mask")))
    t = _joints_shape(_load_npy(path), path, "targets")
    return _with_name(path, lambda: make_signal(t))


def read_keyframes(path: str | Path, frames: int | None = None) -> ControlSignal:
    """In-betweening poses from an .npz with `frames` (K,) frame indices and `poses` (K, 22, 3);
    the motion spans `frames` frames, or the archive's `length` when not given."""
    path = Path(path)
    z = _load_npz(path)
    missing = [k for k in ("frames", "poses") if k not in z]
    if missing:
        raise ValueError(f"{path}: a keyframe file needs 'frames' (K,) and 'poses' (K, 22, 3); "
                         f"missing {', '.join(missing)}")
    idx, poses = np.asarray(z["frames"]), _joints_shape(np.asarray(z["poses"]), path, "poses")
    if idx.ndim != 1 or len(idx) != len(poses) or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"{path}: 'frames' must be K integers for the K poses, got {idx.dtype} {idx.shape} "
                         f"for {len(poses)} poses")
    if len(np.unique(idx)) != len(idx):
        raise ValueError(f"{path}: a frame index appears twice in 'frames'")
    if frames is None:
        if "length" not in z:
            raise ValueError(f"{path}: say how long the motion is (a 'length' entry in the file, or --seconds)")
        try:
            frames = int(np.asarray(z["length"]).reshape(-1)[0])
        except (ValueError, TypeError, IndexError):
            raise ValueError(f"{path}: 'length' must be a frame count, got {z['length']!r}") from None
    return _with_name(path, lambda: keyframe_signal({int(f): p for f, p in zip(idx, poses)}, frames))


def read_motion_joints(path: str | Path) -> np.ndarray:
    """Joint positions (T, 22, 3) of a saved motion: .npy joints, .npz with `joints`, or a
    .bvh; moved to start at the origin facing +Z, where generated motions start."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".bvh":
        from .bvh import BvhError, load_bvh
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        try:
            return load_bvh(path, canonical=True).joints
        except BvhError as e:
            raise ValueError(str(e) if str(path) in str(e) else f"{path}: {e}") from None
    if ext == ".npz":
        z = _load_npz(path)
        if "joints" not in z:
            raise ValueError(f"{path}: no 'joints' array (expected a motion saved as .npz)")
        j = z["joints"]
    elif ext == ".npy":
        j = _load_npy(path)
    else:
        raise ValueError(f"{path}: expected a motion as .npy, .npz or .bvh, got {ext or 'no extension'!r}")
    j = _joints_shape(np.asarray(j, dtype=np.float64), path)
    if len(j) < 2 or not np.isfinite(j).all():
        raise ValueError(f"{path}: needs at least 2 frames of finite positions")
    return canonicalize(j).astype(np.float32)


def path_signal(points, frames: int, height: float | None = None) -> ControlSignal:
    """Pelvis path through 2-D (x, z) points, traversed at constant speed over `frames`.
    The pelvis height stays free unless given."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError(f"path points must be a list of at least two (x, z) pairs, got shape {p.shape}")
    if frames < 2:
        raise ValueError("a path needs at least 2 frames")
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        raise ValueError("path points must not all coincide")
    u = np.linspace(0.0, s[-1], frames)
    x, z = np.interp(u, s, p[:, 0]), np.interp(u, s, p[:, 1])
    targets = np.zeros((frames, sk.NUM_JOINTS, 3))
    mask = np.zeros((frames, sk.NUM_JOINTS, 3), dtype=bool)
    targets[:, 0, 0], targets[:, 0, 2] = x, z
    mask[:, 0, [0, 2]] = True
    if height is not None:
        targets[:, 0, 1] = height
        mask[:, 0, 1] = True
    return make_signal(targets, mask)


def parse_points(text: str) -> np.ndarray:
    """'x,z;x,z;...' (metres) -> (K, 2) points."""
    pts = []
    for k, item in enumerate(p for p in str(text).replace(" ", "").split(";") if p):
        parts = item.split(",")
        try:
            x, z = (float(v) for v in parts)
        except ValueError:
            raise ValueError(f"path point {k + 1} is {item!r}; write points as x,z;x,z;... in metres") from None
        if not (math.isfinite(x) and math.isfinite(z)):
            raise ValueError(f"path point {k + 1} ({item!r}) is not a finite number pair")
        pts.append((x, z))
    if len(pts) < 2:
        raise ValueError(f"a path needs at least two points (x,z;x,z;...), got {text!r}")
    return np.array(pts)


PATH_PRESETS = ("line", "circle", "s-curve", "turn-left", "turn-right")
PRESET_ALIASES = {"straight": "line"}      # the studio's name for a line
DEFAULT_WALK_SPEED = 1.0     # m/s


def preset_name(name: str) -> str:
    """The preset a name (or alias) stands for; ValueError for an unknown one."""
    key = PRESET_ALIASES.get(name, name) if isinstance(name, str) else name
    if key not in PATH_PRESETS:
        raise ValueError(f"path preset must be one of {', '.join(PATH_PRESETS)}, got {name!r}")
    return key


def _arc(cx: float, cz: float, radius: float, start: float, stop: float, n: int) -> np.ndarray:
    a = np.linspace(start, stop, n)
    return np.stack([cx + radius * np.cos(a), cz + radius * np.sin(a)], -1)


def _preset_shape(name: str) -> np.ndarray:
    """Unit-scale polyline from the origin, leaving it heading +Z; left turns go to +X."""
    if name == "line":
        return np.array([[0.0, 0.0], [0.0, 1.0]])
    if name == "circle":
        return _arc(1.0, 0.0, 1.0, math.pi, -math.pi, 97)             # anticlockwise seen from above: to the left
    if name == "s-curve":
        u = np.linspace(0.0, 1.0, 97)                                  # a left bend, then a right one
        return np.stack([0.2 * (1.0 - np.cos(math.pi * u)), u], -1)
    if name in ("turn-left", "turn-right"):
        r = 0.5                                                       # straight, a quarter turn, straight
        path = np.concatenate([[[0.0, 0.0]], _arc(r, 0.6, r, math.pi, math.pi / 2, 33), [[r + 0.6, 0.6 + r]]])
        return path if name == "turn-left" else path * [-1.0, 1.0]
    raise AssertionError(name)


def preset_polyline(name: str, length: float) -> np.ndarray:
    """(N, 2) x, z corner points of a preset path scaled to `length` metres along it."""
    if not isinstance(length, (int, float, np.floating)) or not math.isfinite(length) or length <= 0:
        raise ValueError(f"a path's length must be a positive number of metres, got {length!r}")
    p = _preset_shape(preset_name(name))
    return p * (float(length) / np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def preset_points(name: str, frames: int, speed: float = DEFAULT_WALK_SPEED) -> np.ndarray:
    """(frames, 2) pelvis x, z of a preset path walked at `speed` m/s, one point per frame."""
    key = preset_name(name)
    if not isinstance(frames, (int, np.integer)) or frames < 2:
        raise ValueError(f"a path needs at least 2 frames, got {frames!r}")
    if not isinstance(speed, (int, float)) or not math.isfinite(speed) or not 0 < speed <= 10:
        raise ValueError(f"speed must be in (0, 10] m/s, got {speed!r}")
    p = preset_polyline(key, speed * (frames - 1) / FPS)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    u = np.linspace(0.0, s[-1], frames)
    return np.stack([np.interp(u, s, p[:, 0]), np.interp(u, s, p[:, 1])], -1)


def preset_path(name: str, frames: int, speed: float = DEFAULT_WALK_SPEED,
                height: float | None = None) -> ControlSignal:
    """Pelvis path signal of a preset (line, circle, s-curve, turn-left, turn-right) over
    `frames` frames at a constant `speed` in m/s; the height stays free unless given."""
    return path_signal(preset_points(name, frames, speed), frames, height)


def keyframe_signal(poses: dict[int, np.ndarray], frames: int) -> ControlSignal:
    """In-betweening: whole-body poses (22, 3) fixed at the given frames."""
    targets = np.zeros((frames, sk.NUM_JOINTS, 3))
    mask = np.zeros((frames, sk.NUM_JOINTS), dtype=bool)
    for f, pose in poses.items():
        if not 0 <= f < frames:
            raise ValueError(f"keyframe {f} is outside 0..{frames - 1}")
        targets[f] = np.asarray(pose, dtype=np.float64)
        mask[f] = True
    return make_signal(targets, mask)


def lower_body_signal(joints) -> ControlSignal:
    """Upper-body editing: the given motion's lower body (pelvis, legs) is kept, the rest is free."""
    j = np.asarray(joints, dtype=np.float64)
    mask = np.zeros(j.shape[:2], dtype=bool)
    mask[:, list(sk.LOWER_BODY)] = True
    return make_signal(j, mask)
