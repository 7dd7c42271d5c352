"""Skeleton, motion representation and file formats."""
from .representation import (
    FEATURE_DIM, FPS, Normalizer, canonicalize, features_to_joints, joints_to_features,
    merge_joints, mirror_features, mirror_joints, split_by_joint,
)

__all__ = [
    "FEATURE_DIM", "FPS", "Normalizer", "canonicalize", "features_to_joints",
    "joints_to_features", "merge_joints", "mirror_features", "mirror_joints", "split_by_joint",
]
