"""Control targets for guided generation: global joint positions plus an explicit mask.

Targets are (T, 22, 3) metres in the frame generated motions live in (Y up, starting
at the origin, facing +Z); the mask says which joint coordinates are constrained,
(T, 22) per joint or (T, 22, 3) per coordinate. Nothing is inferred from zeros except
when reading MoLA's files, whose convention it is.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import skeleton as sk


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
    and NaN ones free."""
    t = np.asarray(targets, dtype=np.float64)
    if t.ndim != 3 or t.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"targets must have shape (T, 22, 3), got {t.shape}")
    if mask is None:
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


def read_mola_control(path: str | Path) -> ControlSignal:
    """MoLA's control .npy: (T, 22, 3) global positions, all-zero joints meaning "free".
    A joint is constrained when any of its coordinates is non-zero, so a target that
    happens to sit at x = 0 or z = 0 (the start of a path) stays constrained."""
    path = Path(path)
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable .npy array ({e})") from None
    if a.ndim != 3 or a.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"{path}: expected (T, 22, 3), got {a.shape}")
    joint_mask = (a != 0).any(-1)
    return make_signal(a, joint_mask)


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
