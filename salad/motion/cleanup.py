"""The clean-up every decoded motion gets by default (Pipeline.decode(foot_lock=True)).

Two steps, in this order: the bones are held at the motion's own median lengths (the decoder
lets them stretch by millimetres to centimetres from frame to frame, which reads as jitter and
which no BVH can carry), then planted feet are pinned (salad.motion.footlock). The foot lock's
IK keeps every bone length, so the result stays rigid and its BVH reproduces it.
"""
from __future__ import annotations

import numpy as np

from .bvh_export import rigid_joints
from .footlock import lock_feet_features


def clean_motion(joints: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, dict]:
    """joints (T, 22, 3) decoded from features (T, 263) -> cleaned joints and a report: the foot
    lock's (footlock.FootLockReport.as_dict) plus how far holding the bones moved a joint."""
    rigid = rigid_joints(joints)
    locked, report = lock_feet_features(rigid, features)
    info = report.as_dict()
    moved = np.linalg.norm(rigid - np.asarray(joints, dtype=rigid.dtype), axis=-1)
    info["bones_max_shift_m"] = round(float(moved.max()), 4) if moved.size else 0.0
    info["bones_mean_shift_m"] = round(float(moved.mean()), 4) if moved.size else 0.0
    return locked, info
