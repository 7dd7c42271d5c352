"""BVH import and export for the 22-joint skeleton.

Import reads any BVH, runs forward kinematics, maps named joints onto the 22
HumanML3D joints, converts to metres and resamples to 20 fps. BVH does not record
its units: the reader infers m, cm or mm from the skeleton's size (detect_scale),
so exports in either unit read back alike; scale= overrides the guess. Export
solves per-joint rotations for a 22-joint skeleton with the project's joint names,
in centimetres unless units="m" (salad.motion.bvh_export).

Parser choice: our own NumPy parser. On Bandai clips bvhio gives the same positions
(within 3e-6 m) but needs ~100 ms per clip (up to 270 ms) in per-frame Python loops,
against ~8 ms here; pybvh refuses the Bandai files (position channels on non-root joints).
"""
from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass

import numpy as np

from .bvh_export import UNITS_PER_METRE, bvh_text, save_bvh
from .bvh_mapping import (
    BANDAI_MAPPING, MAPPINGS, MIXAMO_MAPPING, SALAD_MAPPING, SMPL_MAPPING, JointMapping,
    mapped_positions, resolve_mapping,
)
from .bvh_parse import BvhData, BvhError, parse_bvh, parse_bvh_text
from .representation import bone_lengths, canonicalize

__all__ = [
    "BANDAI_MAPPING", "MAPPINGS", "MIXAMO_MAPPING", "SALAD_MAPPING", "SMPL_MAPPING", "UNITS_PER_METRE",
    "BvhClip", "BvhData", "BvhError", "bvh_text", "detect_scale", "load_bvh", "parse_bvh",
    "parse_bvh_text", "resample", "save_bvh",
]

# Metres per file unit that detect_scale chooses between.
UNIT_SCALES = {"m": 1.0, "cm": 0.01, "mm": 0.001}
_TYPICAL_HEIGHT_M = 1.5  # ankle to head along the bones, roughly, of an adult


@dataclass
class BvhClip:
    """A BVH motion on the 22-joint skeleton."""

    joints: np.ndarray        # (T, 22, 3) float32, metres, at `fps`
    fps: float
    source_fps: float
    source_path: str | None
    mapping_name: str
    scale: float = 1.0        # metres per file unit that was applied


def detect_scale(joints: np.ndarray) -> float:
    """Metres per unit of 22-joint positions in unknown units (m, cm or mm).

    Picks the unit that makes the ankle-to-head bone chain closest to an adult's
    in log scale, so the boundaries sit at about 15 units (m/cm) and 474 (cm/mm).
    """
    lengths = bone_lengths(np.asarray(joints, dtype=np.float64))
    chain = lengths[[4, 7, 1, 3, 6, 9, 12, 15]].sum()  # knee, ankle, hip, spine x3, neck, head
    if not np.isfinite(chain) or chain <= 0:
        raise BvhError("cannot infer units: the skeleton has no extent")
    return min(UNIT_SCALES.values(), key=lambda s: abs(math.log(chain * s / _TYPICAL_HEIGHT_M)))


def resample(x: np.ndarray, source_fps: float, fps: float) -> np.ndarray:
    """Linearly interpolate frames (T, ...) sampled at source_fps onto a grid at fps.

    Both grids start at t=0; the output stops at the last source time stamp.
    """
    T = x.shape[0]
    duration = (T - 1) / source_fps
    # The small slack keeps the last frame when the durations agree up to rounding.
    n = int(math.floor(duration * fps + 1e-6)) + 1
    pos = np.arange(n) * (source_fps / fps)
    i0 = np.clip(np.floor(pos + 1e-9).astype(np.int64), 0, max(T - 2, 0))
    frac = np.clip(pos - i0, 0.0, 1.0).reshape((n,) + (1,) * (x.ndim - 1))
    i1 = np.minimum(i0 + 1, T - 1)
    return (1.0 - frac) * x[i0] + frac * x[i1]


def _source_fps(frame_time: float) -> float:
    fps = 1.0 / frame_time
    # Files store 1/30 as 0.0333333: recover the whole rate such a truncation hides.
    nearest = round(fps)
    return float(nearest) if nearest > 0 and abs(fps - nearest) / nearest < 2e-5 else fps


def load_bvh(path: str | os.PathLike, mapping: str | JointMapping = "auto", fps: float | None = 20.0,
             scale: float | None = None, canonical: bool = False) -> BvhClip:
    """Read a BVH file as (T, 22, 3) joints in metres.

    mapping: "auto", a name in MAPPINGS, or a dict {target joint: source name or (a, b, t)}.
    fps: output frame rate (None keeps the file's). scale: metres per file unit
    (None infers m/cm/mm from the skeleton's size, see detect_scale; 0.01 reads a file
    as centimetres). canonical: floor at y=0, start at the origin facing +Z.
    """
    data = parse_bvh(os.fspath(path) if isinstance(path, os.PathLike) else _as_path(path))
    name, table = resolve_mapping(data, mapping)
    joints = mapped_positions(data, table)
    if scale is None:
        try:
            scale = detect_scale(joints)
        except BvhError as e:
            raise BvhError(f"{data.source}: {e}") from None
    elif not _positive(scale):
        raise BvhError(f"{data.source}: scale must be a positive number, got {scale!r}")
    joints = joints * scale
    src_fps = _source_fps(data.frame_time)
    if fps is not None:
        if not _positive(fps):
            raise BvhError(f"{data.source}: fps must be a positive number, got {fps!r}")
        joints = resample(joints, src_fps, fps)
    out_fps = float(fps) if fps is not None else src_fps
    if canonical:
        joints = canonicalize(joints)
    return BvhClip(joints=joints.astype(np.float32), fps=out_fps, source_fps=src_fps,
                   source_path=str(path), mapping_name=name, scale=float(scale))


def _positive(x) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _as_path(path) -> str:
    if not isinstance(path, str):
        raise BvhError(f"expected a file path, got {type(path).__name__}")
    if "\n" in path:
        raise BvhError("load_bvh takes a file path; use parse_bvh_text for BVH text")
    return path
