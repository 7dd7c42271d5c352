"""Real motions as the model takes them: read (BVH, NPY, arrays, a Motion), checked, retargeted
onto the skeleton the model was trained on and turned into raw features of a usable length.
The studio's upload check and real-motion editing (salad.editing.real) both read inputs here."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..checkpoint import CheckpointError, read_checkpoint_config
from ..files import REPO_ROOT
from . import representation as rep
from .bvh import BvhError, load_bvh
from .motion import Motion
from .skeleton import NUM_JOINTS

FEATURE_DIM = rep.FEATURE_DIM
# The training skeleton counts as matched when no bone differs by more than this (metres).
BONE_TOLERANCE_M = 0.005


def input_kind(arr: np.ndarray) -> str | None:
    """"joints" for (T, 22, 3), "features" for (T, 263), None for any other shape."""
    if arr.ndim == 3 and arr.shape[1:] == (NUM_JOINTS, 3):
        return "joints"
    if arr.ndim == 2 and arr.shape[1] == FEATURE_DIM:
        return "features"
    return None


def min_input_frames(kind: str) -> int:
    """The fewest frames an input of `kind` may have: features from joints lose one frame
    (they hold velocities), and the model needs MIN_AUTO_FRAMES of them."""
    return rep.MIN_AUTO_FRAMES + (1 if kind == "joints" else 0)


@dataclass
class RealMotion:
    """A real motion ready for the VAE: raw features (T, 263), T a multiple of 4, and the
    joints they decode to (the reference every error is measured against)."""

    features: np.ndarray
    joints: np.ndarray
    source: str
    info: dict = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return int(self.features.shape[0])


def training_bone_lengths(model_dir: str | os.PathLike | None) -> np.ndarray | None:
    """Bone lengths (22,) of the skeleton a model (a directory holding vae/) was trained on:
    skeleton.json next to the model, or in the VAE's training data directory; None when neither
    is found."""
    root = Path(model_dir) if model_dir else None
    candidates = [] if root is None else [root / "skeleton.json", root / "vae" / "skeleton.json"]
    if root is not None:
        try:
            data_root = read_checkpoint_config(root / "vae", "vae")["meta"]["train_config"]["data"]["root"]
            d = Path(data_root)
            candidates.append((d if d.is_absolute() else REPO_ROOT / d) / "skeleton.json")
        except (CheckpointError, KeyError, TypeError):
            pass
    for c in candidates:
        if c.is_file():
            return read_bone_lengths(c)
    return None


def read_bone_lengths(path: str | os.PathLike) -> np.ndarray:
    """skeleton.json (as written by the dataset builder) -> bone lengths (22,) in metres."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        lengths = np.asarray(doc["bone_lengths_m"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a skeleton file with bone_lengths_m ({e})") from None
    if lengths.shape != (NUM_JOINTS,) or not np.isfinite(lengths).all() or (lengths[1:] <= 0).any():
        raise ValueError(f"{path}: bone_lengths_m must be {NUM_JOINTS} positive lengths")
    return lengths


def resolve_bone_lengths(model_dir: str | os.PathLike | None, bone_lengths=None) -> np.ndarray | None:
    """None (look next to the model), a skeleton.json path or 22 lengths -> (22,) lengths or None."""
    if bone_lengths is None:
        return training_bone_lengths(model_dir)
    if isinstance(bone_lengths, (str, os.PathLike)):
        return read_bone_lengths(bone_lengths)
    lengths = np.asarray(bone_lengths, dtype=np.float64)
    if lengths.shape != (NUM_JOINTS,) or not np.isfinite(lengths).all() or (lengths[1:] <= 0).any():
        raise ValueError(f"bone_lengths must be {NUM_JOINTS} positive lengths in metres, got shape {lengths.shape}")
    return lengths


def _as_array(motion) -> tuple[np.ndarray, str, bool]:
    """-> (array, where, from_bvh) for a path, a Motion or an array."""
    if isinstance(motion, Motion):
        return np.asarray(motion.features), "motion", False
    if isinstance(motion, (str, os.PathLike)):
        path = Path(motion)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        ext = path.suffix.lower()
        if ext == ".bvh":
            try:
                return load_bvh(path, fps=rep.FPS).joints, str(path), True
            except BvhError as e:
                raise ValueError(f"{path}: cannot read BVH ({e})") from None
        if ext == ".npy":
            try:
                return np.load(path, allow_pickle=False), str(path), False
            except (OSError, ValueError) as e:
                raise ValueError(f"{path}: cannot read as a NumPy array ({e})") from None
        raise ValueError(f"{path}: unsupported input type {ext!r}; give a .bvh or .npy file")
    if isinstance(motion, torch.Tensor):
        return motion.detach().cpu().numpy(), "array", False
    if isinstance(motion, np.ndarray):
        return motion, "array", False
    raise ValueError(f"motion must be a BVH/NPY path, a (T, 22, 3) joint array or (T, 263) features, "
                     f"got {type(motion).__name__}")


def load_real_motion(motion, max_frames: int, bone_lengths: np.ndarray | None = None, retarget: bool | None = None,
                     trim: bool = False) -> RealMotion:
    """A BVH/NPY path, joints (T, 22, 3) in metres or raw features (T, 263) -> RealMotion.

    Joints are retargeted onto `bone_lengths` (BVH input always, arrays when some bone
    differs by more than BONE_TOLERANCE_M; retarget=True/False forces it) and
    canonicalised. Up to 3 trailing frames are dropped to reach a multiple of 4; motions
    longer than max_frames are an error unless trim=True keeps their start.
    """
    arr, where, from_bvh = _as_array(motion)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{where}: expected a numeric array, got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=np.float64)
    info: dict = {}
    kind = input_kind(arr)
    if kind == "joints":
        if not np.isfinite(arr).all():
            raise ValueError(f"{where}: joint positions contain NaN or infinite values")
        need = min_input_frames(kind)
        if len(arr) < need:
            raise ValueError(f"{where}: {len(arr)} frames is too short; need at least {need} "
                             f"({need / rep.FPS:.2f} s at {rep.FPS} fps)")
        if bone_lengths is not None:
            differs = float(np.abs(rep.bone_lengths(arr) - bone_lengths).max())
            do = retarget if retarget is not None else (from_bvh or differs > BONE_TOLERANCE_M)
            if do:
                arr = rep.retarget(arr, bone_lengths)
            info["retargeted"], info["bone_length_difference_m"] = bool(do), differs
        else:
            if retarget:
                raise ValueError(f"{where}: cannot retarget: the model's training skeleton (skeleton.json) "
                                 "was not found; pass bone_lengths")
            info["retargeted"] = False
        feats = rep.joints_to_features(rep.canonicalize(arr))
    elif kind == "features":
        if not np.isfinite(arr).all():
            raise ValueError(f"{where}: features contain NaN or infinite values")
        feats = arr
    else:
        raise ValueError(f"{where}: expected joints (T, {NUM_JOINTS}, 3) or features (T, {FEATURE_DIM}), "
                         f"got shape {arr.shape}")
    n = len(feats)
    if n > max_frames:
        if not trim:
            raise ValueError(f"{where}: {n} frames ({n / rep.FPS:.1f} s) is longer than the model's "
                             f"{max_frames} frames ({max_frames / rep.FPS:.1f} s); trim the motion (or pass trim=True)")
        info["trimmed_from_frames"] = n
        n = max_frames
    if n < min_input_frames("features"):
        raise ValueError(f"{where}: {n} feature frames is too short; need at least {min_input_frames('features')}")
    keep = (n // 4) * 4
    info["dropped_frames"] = len(feats) - keep
    feats = feats[:keep].astype(np.float32)
    return RealMotion(feats, rep.features_to_joints(feats).astype(np.float32), where, info)
