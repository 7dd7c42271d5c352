"""The 22-joint HumanML3D/SMPL skeleton and SALAD's body-part hierarchy.

Everything that knows joint indices reads them from here: the kinematic chain,
the joint-wise feature split, the pooling groups 22 -> 12 -> 7, the graph
adjacency at each level and the left/right counterparts at each level.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee",
    "spine2", "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot",
    "neck", "left_collar", "right_collar", "head", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
NUM_JOINTS = len(JOINT_NAMES)

# Chains start at the root or at spine3; the arm chains hang off spine3.
KINEMATIC_CHAINS = (
    (0, 2, 5, 8, 11),
    (0, 1, 4, 7, 10),
    (0, 3, 6, 9, 12, 15),
    (9, 14, 17, 19, 21),
    (9, 13, 16, 18, 20),
)

PARENTS = np.full(NUM_JOINTS, -1, dtype=np.int64)
for _chain in KINEMATIC_CHAINS:
    for _parent, _child in zip(_chain[:-1], _chain[1:]):
        PARENTS[_child] = _parent
del _chain, _parent, _child

# Rest-pose bone directions (character faces +Z, its left is +X, Y is up).
# Used by inverse kinematics: joint rotations take these onto the actual bones.
RAW_OFFSETS = np.array([
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0],
    [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1],
    [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -1, 0],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
], dtype=np.float64)

# Joints whose position defines the facing: right hip, left hip, right shoulder, left shoulder.
FACE_JOINTS = (2, 1, 17, 16)
FOOT_JOINTS_LEFT = (7, 10)
FOOT_JOINTS_RIGHT = (8, 11)
# Order of the four foot-contact channels at the end of the 263-d vector.
CONTACT_JOINTS = FOOT_JOINTS_LEFT + FOOT_JOINTS_RIGHT

LOWER_BODY = (0, 1, 2, 4, 5, 7, 8, 10, 11)
UPPER_BODY = tuple(j for j in range(NUM_JOINTS) if j not in LOWER_BODY)


def _edges_from_parents(parents) -> tuple[tuple[int, int], ...]:
    return tuple((int(p), c) for c, p in enumerate(parents) if p >= 0)


@dataclass(frozen=True)
class SkeletonLevel:
    """One resolution of the pooling hierarchy."""

    names: tuple[str, ...]
    edges: tuple[tuple[int, int], ...]
    mirror_pairs: tuple[tuple[int, int], ...]

    @property
    def size(self) -> int:
        return len(self.names)

    def neighbours(self) -> list[list[int]]:
        """Neighbour lists including the joint itself."""
        nb = [[i] for i in range(self.size)]
        for a, b in self.edges:
            nb[a].append(b)
            nb[b].append(a)
        return [sorted(n) for n in nb]

    def adjacency(self) -> np.ndarray:
        """Binary adjacency with self loops, (n, n)."""
        adj = np.eye(self.size, dtype=np.float32)
        for a, b in self.edges:
            adj[a, b] = adj[b, a] = 1.0
        return adj

    def mirror_index(self) -> np.ndarray:
        """Permutation that sends each joint to its left/right counterpart."""
        perm = np.arange(self.size)
        for a, b in self.mirror_pairs:
            perm[a], perm[b] = b, a
        return perm


JOINTS_22 = SkeletonLevel(
    names=JOINT_NAMES,
    edges=_edges_from_parents(PARENTS),
    mirror_pairs=((1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21)),
)

JOINTS_12 = SkeletonLevel(
    names=("root", "left_hip", "left_leg", "right_hip", "right_leg", "spine",
           "chest", "left_shoulder", "left_arm", "right_shoulder", "right_arm", "head"),
    edges=((0, 1), (0, 3), (0, 5), (1, 2), (3, 4), (5, 6), (6, 7), (6, 9), (6, 11), (7, 8), (9, 10)),
    mirror_pairs=((1, 3), (2, 4), (7, 9), (8, 10)),
)

BODY_PARTS = SkeletonLevel(
    names=("root", "left_lower", "right_lower", "spine", "left_upper", "right_upper", "head"),
    edges=((0, 1), (0, 2), (0, 3), (3, 4), (3, 5), (3, 6)),
    mirror_pairs=((1, 2), (4, 5)),
)
LEVELS = (JOINTS_22, JOINTS_12, BODY_PARTS)

# Which finer joints each coarser joint summarises (SALAD supp. Fig. 2).
POOL_22_TO_12 = (
    (0, 1, 2, 3), (0, 1, 4), (4, 7, 10), (0, 2, 5), (5, 8, 11), (0, 3, 6, 9),
    (9, 6, 12, 13, 14), (9, 13, 16), (16, 18, 20), (9, 14, 17), (17, 19, 21), (9, 12, 15),
)
POOL_12_TO_7 = ((0, 1, 3, 5), (0, 1, 2), (0, 3, 4), (0, 5, 6), (6, 7, 8), (6, 9, 10), (6, 11))
POOL_GROUPS = (POOL_22_TO_12, POOL_12_TO_7)

# Body-part groups used by attention mirroring: lower = legs, upper = arms.
PART_MIRROR_PAIRS = {"lower": ((1, 2),), "upper": ((4, 5),), "all": ((1, 2), (4, 5))}
# BODY_PARTS of each half of the body; the root part carries the root's path.
PART_GROUPS = {"lower": (0, 1, 2), "upper": (3, 4, 5, 6)}


def pooling_matrix(groups, n_fine: int) -> np.ndarray:
    """Row-normalised (n_coarse, n_fine) averaging matrix."""
    m = np.zeros((len(groups), n_fine), dtype=np.float32)
    for i, g in enumerate(groups):
        m[i, list(g)] = 1.0 / len(g)
    return m


def unpooling_matrix(groups, n_fine: int) -> np.ndarray:
    """(n_fine, n_coarse) matrix that averages the coarse joints covering each fine joint.

    SALAD's public code sums them, which makes the root four times louder than a
    wrist; averaging keeps every fine joint on the same scale.
    """
    m = np.zeros((n_fine, len(groups)), dtype=np.float32)
    for i, g in enumerate(groups):
        m[list(g), i] = 1.0
    return m / m.sum(axis=1, keepdims=True)


# The body part (0..6) that owns each of the 22 joints, for colouring joints by
# part and tinting them by per-part attention.
PART_OF_JOINT = np.array([
    0,        # pelvis: root
    1, 2,     # hips
    3,        # spine1
    1, 2,     # knees
    3,        # spine2
    1, 2,     # ankles
    3,        # spine3
    1, 2,     # feet
    6,        # neck
    4, 5,     # collars
    6,        # head
    4, 5, 4, 5, 4, 5,  # shoulders, elbows, wrists
], dtype=np.int64)
