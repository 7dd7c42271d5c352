"""Per-motion measures of the editing benchmark: did an edit reach its target, and what did it keep.

Every function takes joints (T, 22, 3) in metres (Y up, 20 fps) and is vectorised over frames. Motions
compared with each other must have the same length: the benchmark generates them with a fixed length.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.stats import spearmanr

from ..motion import skeleton as sk
from ..motion.representation import FPS
from .physics import PELVIS, check_joints, heading

SIDES = ("left", "right")
_OTHER = {"left": "right", "right": "left"}

# Body-part joint sets whose pose an edit of the other parts should leave alone.
JOINT_SETS: dict[str, tuple[int, ...]] = {
    "all": tuple(range(sk.NUM_JOINTS)),
    "lower": sk.LOWER_BODY,
    "upper": sk.UPPER_BODY,
}


def _pair(a, b) -> tuple[np.ndarray, np.ndarray]:
    a, b = check_joints(a, "motion"), check_joints(b, "reference")
    if a.shape != b.shape:
        raise ValueError(f"motions to compare must have the same length: {a.shape[0]} vs {b.shape[0]} frames")
    return a, b


def other_side(side: str) -> str:
    """left <-> right; any other label (none, both) has no counterpart and stays as it is."""
    return _OTHER.get(side, side)


def side_flipped(before: str, after: str) -> bool:
    """True when a one-sided label (left/right) turned into the other side."""
    return before in SIDES and after == _OTHER[before]


def dominant_wrist(left_path: float, right_path: float) -> str:
    """The side whose wrist travels further (physics.physical_checks' wrist path lengths)."""
    return "left" if left_path > right_path else "right"


def root_trajectory_distance(joints, reference) -> float:
    """Mean horizontal distance (m) between the two pelvis paths once both start at the same point.

    Generated motions all start facing +Z, so no rotation is aligned: a turn the other way counts.
    """
    a, b = _pair(joints, reference)
    pa = a[:, PELVIS, [0, 2]] - a[:1, PELVIS, [0, 2]]
    pb = b[:, PELVIS, [0, 2]] - b[:1, PELVIS, [0, 2]]
    return float(np.linalg.norm(pa - pb, axis=-1).mean())


def speed_profile(joints, fps: float = FPS) -> np.ndarray:
    """(T - 1,) mean speed of all joints per frame step (m/s): the motion's rhythm (steps, wave strokes)."""
    j = check_joints(joints, "joints")
    return np.linalg.norm(np.diff(j, axis=0), axis=-1).mean(axis=1) * fps


def timing_correlation(joints, reference) -> float:
    """Pearson correlation of the two speed profiles: 1 = the same rhythm frame by frame.

    Two motionless clips count as identical in timing (1), a motionless clip against a moving one as 0.
    """
    a, b = _pair(joints, reference)
    sa, sb = speed_profile(a), speed_profile(b)
    da, db = sa - sa.mean(), sb - sb.mean()
    na, nb = np.linalg.norm(da), np.linalg.norm(db)
    if na < 1e-9 or nb < 1e-9:
        return 1.0 if (na < 1e-9 and nb < 1e-9) else 0.0
    return float(np.clip(da @ db / (na * nb), -1.0, 1.0))


def body_frame(joints) -> np.ndarray:
    """Joints relative to the pelvis' ground point, turned so that the body faces +Z in every frame
    (heights stay absolute, so crouching shows)."""
    j = check_joints(joints, "joints")
    yaw = heading(j)
    rel = j.copy()
    rel[..., [0, 2]] -= j[:, PELVIS:PELVIS + 1, [0, 2]]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    out = rel.copy()
    out[..., 0] = c * rel[..., 0] - s * rel[..., 2]
    out[..., 2] = s * rel[..., 0] + c * rel[..., 2]
    return out


def pose_distance(joints, reference, joint_set: str | Sequence[int] = "all") -> float:
    """MPJPE (m) in the body frame over a set of joints ("all", "lower", "upper" or indices): how much the
    pose changed, whatever the global path did."""
    a, b = _pair(joints, reference)
    idx = JOINT_SETS[joint_set] if isinstance(joint_set, str) else tuple(int(i) for i in joint_set)
    if not idx or min(idx) < 0 or max(idx) >= sk.NUM_JOINTS:
        raise ValueError(f"joint set must name joints 0..{sk.NUM_JOINTS - 1}, got {joint_set!r}")
    fa, fb = body_frame(a)[:, idx], body_frame(b)[:, idx]
    return float(np.linalg.norm(fa - fb, axis=-1).mean())


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman rank correlation; 0 when either side is constant (no ordering to agree with)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1 or len(x) < 2:
        raise ValueError(f"spearman needs two equally long 1-d sequences of >= 2 values, got {x.shape} and {y.shape}")
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return 0.0
    return float(spearmanr(x, y).statistic)


def is_monotonic(values: Sequence[float], increasing: bool = True) -> bool:
    """True when the values never step the wrong way (ties allowed) and are not all equal."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1 or len(v) < 2:
        raise ValueError(f"need a 1-d sequence of at least 2 values, got shape {v.shape}")
    d = np.diff(v) if increasing else -np.diff(v)
    return bool((d >= 0).all() and (d > 0).any())


# ---------------------------------------------------------------- real motions and their reconstructions
# (these take motions of different lengths where they say so)


def mpjpe(a: np.ndarray, b: np.ndarray, root_relative: bool = True) -> float:
    """Mean per-joint position error (metres) of two (T, 22, 3) motions; root_relative
    compares poses with the pelvis at the origin (the VAE's MPJPE), otherwise it also
    counts where the body is."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"mpjpe needs two motions of one shape, got {a.shape} and {b.shape}")
    if root_relative:
        a, b = a - a[:, :1], b - b[:, :1]
    return float(np.linalg.norm(a - b, axis=-1).mean())


def root_path_error(a: np.ndarray, b: np.ndarray) -> float:
    """Mean horizontal distance (metres) between two motions' pelvis paths, frame by frame
    over the shorter one."""
    n = min(len(a), len(b))
    return float(np.linalg.norm(np.asarray(a)[:n, 0, [0, 2]] - np.asarray(b)[:n, 0, [0, 2]], axis=-1).mean())


def root_path_deviation(a: np.ndarray, b: np.ndarray) -> float:
    """Mean horizontal distance (metres) from each pelvis position of `a` to the polyline of
    b's pelvis path: how far a leaves b's path, whatever its speed along it."""
    p = np.asarray(a, np.float64)[:, 0, [0, 2]]
    q = np.asarray(b, np.float64)[:, 0, [0, 2]]
    if len(q) == 1:
        return float(np.linalg.norm(p - q, axis=-1).mean())
    start, seg = q[:-1], np.diff(q, axis=0)                                   # (S, 2)
    rel = p[:, None] - start[None]                                           # (P, S, 2)
    along = np.clip((rel * seg).sum(-1) / np.maximum((seg * seg).sum(-1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(rel - along[..., None] * seg, axis=-1).min(axis=1).mean())
