"""HumanML3D's 263-d motion features, and their joint-wise split for SALAD.

Layout of one frame (J = 22):
    0        root yaw velocity (half the yaw angle per frame, as HumanML3D stores it)
    1:3      root XZ velocity in the facing frame
    3        root height
    4:67     joints 1..21 relative to the root's XZ, rotated to face +Z ("ric")
    67:193   joints 1..21 6D rotations from inverse kinematics
    193:259  velocities of all 22 joints in the facing frame
    259:263  foot contacts: left ankle, left toe, right ankle, right toe

Every function takes NumPy arrays or torch tensors with any leading batch dims
and returns the same kind. Work happens in torch, vectorised over frames.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch

import salad.motion.skeleton as sk
from .quaternion import qbetween, qinv, qmul, qrot, quat_to_cont6d

FEATURE_DIM = 263
FPS = 20
# The shortest motion the model makes or takes: 4 latent frames (the VAE's latent has T/4 frames).
MIN_AUTO_FRAMES = 16
ROOT_SLICE = slice(0, 4)
RIC_SLICE = slice(4, 4 + 21 * 3)
ROT_SLICE = slice(67, 67 + 21 * 6)
VEL_SLICE = slice(193, 193 + 22 * 3)
CONTACT_SLICE = slice(259, 263)
FOOT_CONTACT_THRESHOLD = 0.002  # squared displacement per frame, m^2
FORWARD_SMOOTHING_SIGMA = 20.0  # frames


# ---------------------------------------------------------------- array plumbing

def _as_torch(x, dtype=None):
    """(tensor, restore) where restore maps a result back to x's kind and dtype."""
    if isinstance(x, torch.Tensor):
        return (x if dtype is None else x.to(dtype)), (lambda y: y.to(x.dtype))
    arr = np.asarray(x)
    if not np.issubdtype(arr.dtype, np.floating):
        raise TypeError(f"expected a float array, got dtype {arr.dtype}")
    t = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float64))
    return t, (lambda y: y.detach().cpu().numpy().astype(arr.dtype, copy=False))


def _check_joints(j: torch.Tensor, min_frames: int = 1) -> None:
    if j.ndim < 3 or j.shape[-2:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"joints must have shape (..., T, 22, 3), got {tuple(j.shape)}")
    if j.shape[-3] < min_frames:
        raise ValueError(f"need at least {min_frames} frames, got {j.shape[-3]}")


def _check_features(f: torch.Tensor, dim: int = FEATURE_DIM) -> None:
    if f.ndim < 2 or f.shape[-1] != dim:
        raise ValueError(f"features must have shape (..., T, {dim}), got {tuple(f.shape)}")


# ---------------------------------------------------------------- facing and IK

def _gaussian_smooth_time(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian filter along dim -2 with edge replication (scipy's mode='nearest', truncate=4)."""
    radius = int(4.0 * sigma + 0.5)
    k = torch.arange(-radius, radius + 1, dtype=x.dtype)
    w = torch.exp(-0.5 * (k / sigma) ** 2)
    w = w / w.sum()
    lead, T, C = x.shape[:-2], x.shape[-2], x.shape[-1]
    flat = x.reshape(-1, T, C).transpose(1, 2).reshape(-1, 1, T)
    idx = torch.arange(-radius, T + radius).clamp(0, T - 1)
    padded = flat[..., idx]
    out = torch.nn.functional.conv1d(padded, w.view(1, 1, -1))
    return out.reshape(-1, C, T).transpose(1, 2).reshape(lead + (T, C))


def facing_direction(joints: torch.Tensor, smooth: bool = False) -> torch.Tensor:
    """Horizontal unit forward vector per frame, (..., T, 3).

    Mirrors HumanML3D's IK exactly, including its use of the face joints in the
    order (right hip, left hip, right shoulder, left shoulder) unpacked as
    (l_hip, r_hip, sdr_r, sdr_l): the hips enter with the opposite sign to the
    shoulders, and the wider shoulders decide the direction. Keeping this makes
    features computed here interchangeable with the released dataset.
    """
    a, b, c, d = sk.FACE_JOINTS
    across = (joints[..., b, :] - joints[..., a, :]) + (joints[..., c, :] - joints[..., d, :])
    across = across / across.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    up = across.new_tensor([0.0, 1.0, 0.0]).expand_as(across)
    forward = torch.cross(up, across, dim=-1)
    if smooth:
        forward = _gaussian_smooth_time(forward, FORWARD_SMOOTHING_SIGMA)
    return forward / forward.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def _initial_facing(joints: torch.Tensor) -> torch.Tensor:
    """Frame-0 forward from hips and shoulders, right minus left (as HumanML3D's canonicalisation)."""
    rh, lh, rs, ls = sk.FACE_JOINTS
    j0 = joints[..., 0, :, :]
    across = (j0[..., rh, :] - j0[..., lh, :]) + (j0[..., rs, :] - j0[..., ls, :])
    across = across / across.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    up = across.new_tensor([0.0, 1.0, 0.0]).expand_as(across)
    forward = torch.cross(up, across, dim=-1)
    forward = forward * forward.new_tensor([1.0, 0.0, 1.0])
    return forward / forward.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def inverse_kinematics(joints: torch.Tensor, smooth_forward: bool = True) -> torch.Tensor:
    """Local joint quaternions (..., T, 22, 4) taking RAW_OFFSETS directions onto the bones.

    Joint 0 holds the root (facing) rotation; frame 0's is the identity, so the
    features assume the motion starts facing +Z. Rotations are shortest-arc, so
    they carry no twist: positions determine them.
    """
    forward = facing_direction(joints, smooth=smooth_forward)
    target = forward.new_tensor([0.0, 0.0, 1.0]).expand_as(forward)
    root = qbetween(forward, target).clone()
    root[..., 0, :] = root.new_tensor([1.0, 0.0, 0.0, 0.0])
    quats = joints.new_zeros(joints.shape[:-1] + (4,))
    quats[..., 0, :] = root
    raw = torch.as_tensor(sk.RAW_OFFSETS, dtype=joints.dtype)
    for chain in sk.KINEMATIC_CHAINS:
        R = root
        for parent, child in zip(chain[:-1], chain[1:]):
            bone = joints[..., child, :] - joints[..., parent, :]
            bone = bone / bone.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            world = qbetween(raw[child].expand_as(bone), bone)
            local = qmul(qinv(R), world)
            quats[..., child, :] = local
            R = qmul(R, local)
    return quats


def forward_kinematics(quats: torch.Tensor, root_pos: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Joint positions (..., 22, 3) from local quaternions (..., 22, 4), root position (..., 3)
    and per-joint offset vectors (22, 3) in the RAW_OFFSETS convention."""
    joints = [None] * sk.NUM_JOINTS
    joints[0] = root_pos
    for chain in sk.KINEMATIC_CHAINS:
        R = quats[..., 0, :]
        for parent, child in zip(chain[:-1], chain[1:]):
            R = qmul(R, quats[..., child, :])
            joints[child] = qrot(R, offsets[child].expand(R.shape[:-1] + (3,))) + joints[parent]
    return torch.stack(joints, dim=-2)


def bone_lengths(joints) -> np.ndarray:
    """Median length of each bone (child joint 1..21 to its parent), (22,) with 0 at the root."""
    j, _ = _as_torch(joints)
    _check_joints(j)
    flat = j.reshape(-1, sk.NUM_JOINTS, 3)
    lengths = torch.zeros(sk.NUM_JOINTS, dtype=j.dtype)
    for child in range(1, sk.NUM_JOINTS):
        lengths[child] = (flat[:, child] - flat[:, sk.PARENTS[child]]).norm(dim=-1).median()
    return lengths.numpy()


def retarget(joints, lengths):
    """Re-pose a motion onto a skeleton with the given bone lengths (22,), keeping bone
    directions; the root path is scaled by the ratio of leg lengths (HumanML3D's rule)."""
    j, restore = _as_torch(joints)
    _check_joints(j)
    target = torch.as_tensor(np.asarray(lengths), dtype=j.dtype)
    source = torch.as_tensor(bone_lengths(j.detach()), dtype=j.dtype)
    leg = list(sk.KINEMATIC_CHAINS[1][1:4])  # hip->knee->ankle
    scale = target[leg].sum() / source[leg].sum().clamp_min(1e-8)
    quats = inverse_kinematics(j, smooth_forward=False)
    offsets = torch.as_tensor(sk.RAW_OFFSETS, dtype=j.dtype) * target[:, None]
    out = forward_kinematics(quats, j[..., 0, :] * scale, offsets)
    return restore(out)


# ---------------------------------------------------------------- canonicalisation

def canonicalize(joints):
    """Put the lowest joint on the floor (y=0), the frame-0 root at the XZ origin and
    turn the motion so that frame 0 faces +Z. Returns the same kind as the input."""
    j, restore = _as_torch(joints)
    _check_joints(j)
    floor = j[..., 1].amin(dim=(-1, -2), keepdim=True)
    j = j - torch.stack((torch.zeros_like(floor), floor, torch.zeros_like(floor)), dim=-1)
    root0 = j[..., :1, :1, :] * j.new_tensor([1.0, 0.0, 1.0])
    j = j - root0
    forward = _initial_facing(j)
    q = qbetween(forward, forward.new_tensor([0.0, 0.0, 1.0]).expand_as(forward))
    j = qrot(q[..., None, None, :].expand(j.shape[:-1] + (4,)), j)
    return restore(j)


# ---------------------------------------------------------------- joints -> features

def foot_contacts(joints: torch.Tensor, threshold: float = FOOT_CONTACT_THRESHOLD) -> torch.Tensor:
    """(..., T-1, 4) in CONTACT_JOINTS order: 1 where the joint moved less than the threshold."""
    feet = joints[..., list(sk.CONTACT_JOINTS), :]
    disp = ((feet[..., 1:, :, :] - feet[..., :-1, :, :]) ** 2).sum(-1)
    return (disp < threshold).to(joints.dtype)


def joints_to_features(joints, feet_threshold: float = FOOT_CONTACT_THRESHOLD):
    """Global joint positions (..., T, 22, 3) in metres, Y-up -> features (..., T-1, 263).

    Does not canonicalise: call canonicalize() first for dataset building. The
    facing at frame 0 defines the features' reference frame either way.
    """
    j, restore = _as_torch(joints)
    _check_joints(j, min_frames=2)
    quats = inverse_kinematics(j, smooth_forward=True)
    r_rot = quats[..., 0, :]                       # (..., T, 4)
    cont6d = quat_to_cont6d(quats)                 # (..., T, 22, 6)

    root = j[..., 0, :]
    root_vel = qrot(r_rot[..., 1:, :], root[..., 1:, :] - root[..., :-1, :])
    r_vel = qmul(r_rot[..., 1:, :], qinv(r_rot[..., :-1, :]))
    yaw_vel = torch.asin(r_vel[..., 2:3].clamp(-1.0, 1.0))

    local = j - root[..., None, :] * j.new_tensor([1.0, 0.0, 1.0])
    ric = qrot(r_rot[..., None, :].expand(local.shape[:-1] + (4,)), local)

    world_vel = j[..., 1:, :, :] - j[..., :-1, :, :]
    vel = qrot(r_rot[..., :-1, None, :].expand(world_vel.shape[:-1] + (4,)), world_vel)

    lead = j.shape[:-3]
    T1 = j.shape[-3] - 1
    feats = torch.cat((
        yaw_vel,
        root_vel[..., [0, 2]],
        ric[..., :-1, 0, 1:2],
        ric[..., :-1, 1:, :].reshape(lead + (T1, 63)),
        cont6d[..., :-1, 1:, :].reshape(lead + (T1, 126)),
        vel.reshape(lead + (T1, 66)),
        foot_contacts(j, feet_threshold),
    ), dim=-1)
    return restore(feats)


# ---------------------------------------------------------------- features -> joints

def root_rotation_and_position(features: torch.Tensor):
    """Integrate the root channels: yaw quaternion (..., T, 4) and position (..., T, 3)."""
    yaw_half = features[..., 0]
    angle = torch.zeros_like(yaw_half)
    angle[..., 1:] = yaw_half[..., :-1]
    angle = torch.cumsum(angle, dim=-1)
    zero = torch.zeros_like(angle)
    r_rot = torch.stack((torch.cos(angle), zero, torch.sin(angle), zero), dim=-1)
    step = torch.zeros(features.shape[:-1] + (3,), dtype=features.dtype, device=features.device)
    step[..., 1:, 0] = features[..., :-1, 1]
    step[..., 1:, 2] = features[..., :-1, 2]
    pos = torch.cumsum(qrot(qinv(r_rot), step), dim=-2)
    pos = torch.stack((pos[..., 0], features[..., 3], pos[..., 2]), dim=-1)
    return r_rot, pos


def features_to_joints(features):
    """Features (..., T, 263) -> global joint positions (..., T, 22, 3), from the ric channels."""
    f, restore = _as_torch(features)
    _check_features(f)
    r_rot, root = root_rotation_and_position(f)
    ric = f[..., RIC_SLICE].reshape(f.shape[:-1] + (21, 3))
    inv = qinv(r_rot)[..., None, :].expand(ric.shape[:-1] + (4,))
    body = qrot(inv, ric)
    body = body + (root * root.new_tensor([1.0, 0.0, 1.0]))[..., None, :]
    return restore(torch.cat((root[..., None, :], body), dim=-2))


# ---------------------------------------------------------------- joint-wise split (SALAD)

@lru_cache(maxsize=None)
def joint_feature_indices() -> tuple[tuple[int, ...], ...]:
    """For each joint, the indices into the 263-d vector that form its own feature vector.

    Root: its 4 root channels and its velocity (7). Joint i: ric, 6D rotation and
    velocity (12), plus its contact channel for ankles and toes (13).
    """
    out = [tuple(range(0, 4)) + tuple(range(193, 196))]
    for i in range(1, sk.NUM_JOINTS):
        idx = list(range(4 + 3 * (i - 1), 4 + 3 * i))
        idx += range(67 + 6 * (i - 1), 67 + 6 * i)
        idx += range(193 + 3 * i, 196 + 3 * i)
        if i in sk.CONTACT_JOINTS:
            idx.append(259 + sk.CONTACT_JOINTS.index(i))
        out.append(tuple(idx))
    flat = sorted(i for g in out for i in g)
    assert flat == list(range(FEATURE_DIM)), "joint split must cover every channel once"
    return tuple(out)


def split_by_joint(features: torch.Tensor) -> list[torch.Tensor]:
    """(..., 263) -> list of 22 tensors (..., D_j)."""
    return [features[..., list(idx)] for idx in joint_feature_indices()]


def merge_joints(parts: list[torch.Tensor]) -> torch.Tensor:
    """Exact inverse of split_by_joint."""
    if len(parts) != sk.NUM_JOINTS:
        raise ValueError(f"expected {sk.NUM_JOINTS} joint feature tensors, got {len(parts)}")
    cat = torch.cat(parts, dim=-1)
    return cat[..., torch.tensor(_MERGED_POSITIONS, device=cat.device)]


# where each of the 263 channels lies in the joints' parts concatenated; a plain tuple, which torch.compile (of the
# decoder) reads as a constant
_MERGED_POSITIONS = tuple(sorted(range(FEATURE_DIM), key=[i for g in joint_feature_indices() for i in g].__getitem__))


# ---------------------------------------------------------------- mirroring

def mirror_joints(joints):
    """Reflect across the YZ plane and swap left/right joints."""
    j, restore = _as_torch(joints)
    _check_joints(j)
    out = j[..., sk.JOINTS_22.mirror_index(), :] * j.new_tensor([-1.0, 1.0, 1.0])
    return restore(out)


@lru_cache(maxsize=None)
def _feature_mirror_plan() -> tuple[np.ndarray, np.ndarray]:
    """(permutation, sign) such that mirrored = features[..., perm] * sign."""
    perm = np.arange(FEATURE_DIM)
    sign = np.ones(FEATURE_DIM)
    sign[0] = -1.0          # yaw velocity turns the other way
    sign[1] = -1.0          # sideways root velocity
    swap = sk.JOINTS_22.mirror_index()
    for i in range(1, sk.NUM_JOINTS):
        src = swap[i]
        for k in range(3):
            perm[4 + 3 * (i - 1) + k] = 4 + 3 * (src - 1) + k
        # Reflection conjugates each rotation: R' = M R M with M = diag(-1, 1, 1).
        # Column 0 of R' is (r00, -r10, -r20); column 1 is (-r01, r11, r21).
        for k, s in enumerate((1, -1, -1, -1, 1, 1)):
            perm[67 + 6 * (i - 1) + k] = 67 + 6 * (src - 1) + k
            sign[67 + 6 * (i - 1) + k] = s
        sign[4 + 3 * (i - 1)] = -1.0
    for i in range(sk.NUM_JOINTS):
        src = swap[i]
        for k in range(3):
            perm[193 + 3 * i + k] = 193 + 3 * src + k
        sign[193 + 3 * i] = -1.0
    contact_swap = [sk.CONTACT_JOINTS.index(swap[j]) for j in sk.CONTACT_JOINTS]
    perm[259:263] = 259 + np.array(contact_swap)
    return perm, sign


def mirror_features(features):
    """Mirror 263-d features; consistent with mirror_joints under joints_to_features."""
    f, restore = _as_torch(features)
    _check_features(f)
    perm, sign = _feature_mirror_plan()
    return restore(f[..., perm] * torch.as_tensor(sign, dtype=f.dtype))


# ---------------------------------------------------------------- normalisation

class Normalizer:
    """Per-channel mean/std normalisation of features."""

    def __init__(self, mean, std, eps: float = 1e-8):
        mean = np.asarray(mean, dtype=np.float32)
        std = np.asarray(std, dtype=np.float32)
        if mean.shape != std.shape or mean.ndim != 1:
            raise ValueError(f"mean and std must be equal 1-d shapes, got {mean.shape} and {std.shape}")
        if not (np.isfinite(mean).all() and np.isfinite(std).all()) or (std <= 0).any():
            raise ValueError("std must be positive and finite, mean finite")
        self.mean, self.std, self.eps = mean, std, eps

    @property
    def dim(self) -> int:
        return self.mean.shape[0]

    def _stats(self, like):
        if isinstance(like, torch.Tensor):
            return (torch.as_tensor(self.mean, dtype=like.dtype, device=like.device),
                    torch.as_tensor(self.std, dtype=like.dtype, device=like.device))
        return self.mean, self.std

    def normalize(self, x):
        mean, std = self._stats(x)
        return (x - mean) / (std + self.eps)

    def denormalize(self, x):
        mean, std = self._stats(x)
        return x * (std + self.eps) + mean


def feature_statistics(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std over all frames of (N, 263) stacked features, with HumanML3D's
    grouping: one shared std per group of channels (root yaw, root XZ velocity,
    root height, ric, rotations, velocities, contacts), so no single noisy channel
    dominates. A floor keeps near-constant groups from blowing up."""
    f = np.asarray(features, dtype=np.float64)
    _check_features(torch.from_numpy(f[:1]))
    mean = f.mean(axis=0)
    std = f.std(axis=0)
    groups = [slice(0, 1), slice(1, 3), slice(3, 4), RIC_SLICE, ROT_SLICE, VEL_SLICE, CONTACT_SLICE]
    for g in groups:
        std[g] = std[g].mean()
    std = np.maximum(std, 1e-3)
    return mean.astype(np.float32), std.astype(np.float32)
