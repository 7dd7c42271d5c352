"""Writing 22-joint motions as BVH: rest skeleton from the motion, rotations by inverse kinematics.

Units are centimetres by default, what Maya, MotionBuilder and most mocap files use;
units="m" writes metres, which Blender's BVH importer takes at its default scale (it
maps one BVH unit to one metre; import a centimetre file with Scale 0.01). BVH has no
field for units: readers infer them (salad.motion.bvh.load_bvh from the skeleton's size).

The rest skeleton has each bone's median length over the motion, and each joint aims
its bone from where the rest skeleton has put the joint at the motion's child joint.
A re-read child then lies on the line to its true position, off by the difference
between that distance and its bone's rest length (children of the pelvis and spine3
also by how far their arrangement strays from its median). Motions on a rigid
skeleton (datasets, and the 263-d representation of one) come back exactly, up to
the printed decimals; generated motions, whose bone lengths drift frame to frame,
come back off by that drift, which fixed BVH offsets cannot follow.

The rest pose stands upright facing +Z with the character's left at +X and the arms
out sideways (T-pose): with the arms at rest pointing down, an arm raised overhead
would sit at the 180-degree singularity of the shortest-arc rotation and its twist
could flip between frames.

Pelvis and spine3 get one rotation fitted (Kabsch) to all their child bones;
every other joint turns its rest bone onto the aimed bone by the shortest arc
in its parent's frame (minimal twist), which stays continuous in time. Giving
the thigh and upper arm the twist of the knee/elbow bend plane instead was
tried: it jumps whenever a limb goes from straight to bent.
"""
from __future__ import annotations

import math
import numbers
import os
from pathlib import Path

import numpy as np
import torch

from . import skeleton as sk
from .bvh_parse import BvhError
from .quaternion import matrix_to_euler, qbetween, quat_to_matrix
from .representation import bone_lengths
from ..files import atomic_write_text

# Rest direction of the bone from each joint's parent to the joint.
REST_DIRECTIONS = sk.RAW_OFFSETS.copy()
for _j in (16, 18, 20):      # left shoulder, elbow, wrist: arms out to the side
    REST_DIRECTIONS[_j] = (1.0, 0.0, 0.0)
for _j in (17, 19, 21):
    REST_DIRECTIONS[_j] = (-1.0, 0.0, 0.0)
REST_DIRECTIONS[15] = (0.0, 1.0, 0.0)  # head above the neck
del _j

CHILDREN = tuple(tuple(int(c) for c in np.flatnonzero(sk.PARENTS == j)) for j in range(sk.NUM_JOINTS))
# Joints with several children get a frame fitted to all of them: (left, right, up) child.
FRAME_CHILDREN = {0: (1, 2, 3), 9: (13, 14, 12)}

# File units per metre for each unit save_bvh writes.
UNITS_PER_METRE = {"cm": 100.0, "m": 1.0}
DEFAULT_UNITS = "cm"

# Euler order per joint, outermost first. The middle angle is the one that can
# reach gimbal lock, so it goes to the axis that turns least: the bone's own axis
# (twist, which minimal-twist IK keeps small) for limbs and spine, and pitch for
# the root, whose yaw is unbounded. On Bandai clips no middle angle passes 75 deg.
_ORDER_BY_BONE_AXIS = {0: "ZXY", 1: "ZYX", 2: "YZX"}


def _euler_order(j: int) -> str:
    if j == 0:
        return "YXZ"
    kids = CHILDREN[j]
    if not kids:
        return "ZXY"  # leaves never rotate
    bone = (0.0, 1.0, 0.0) if j in FRAME_CHILDREN else REST_DIRECTIONS[kids[0]]
    return _ORDER_BY_BONE_AXIS[int(np.argmax(np.abs(bone)))]


EULER_ORDERS = tuple(_euler_order(j) for j in range(sk.NUM_JOINTS))


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _child_frame(j: torch.Tensor, joint: int) -> torch.Tensor:
    """(T, 3, 3) orthonormal frame of a multi-child joint: columns left, up, forward."""
    left, right, up = FRAME_CHILDREN[joint]
    x = _unit(j[:, left] - j[:, right])
    y = j[:, up] - j[:, joint]
    y = _unit(y - (y * x).sum(-1, keepdim=True) * x)
    z = torch.cross(x, y, dim=-1)
    return torch.stack((x, y, z), dim=-1)


def _kabsch(rest: torch.Tensor, actual: torch.Tensor) -> torch.Tensor:
    """Rotations (T, 3, 3) that best take rest vectors (K, 3) onto actual vectors (T, K, 3)."""
    h = actual.transpose(-1, -2) @ rest                      # sum_k a_k r_k^T
    u, _, vh = torch.linalg.svd(h)
    d = torch.sign(torch.linalg.det(u @ vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    fix = torch.ones(h.shape[:-1], dtype=h.dtype)
    fix[:, 2] = d
    return (u * fix.unsqueeze(-2)) @ vh


def rest_offsets(joints: torch.Tensor) -> torch.Tensor:
    """(22, 3) rest offsets of each joint from its parent, from the motion's own proportions.

    Children of multi-child joints keep their median placement in that joint's
    frame; every other bone points along REST_DIRECTIONS with its median length.
    """
    lengths = torch.as_tensor(bone_lengths(joints.numpy()), dtype=joints.dtype)
    offsets = torch.as_tensor(REST_DIRECTIONS, dtype=joints.dtype) * lengths[:, None]
    for joint, kids in FRAME_CHILDREN.items():
        frame = _child_frame(joints, joint)
        for c in kids:
            local = (frame.transpose(-1, -2) @ (joints[:, c] - joints[:, joint]).unsqueeze(-1)).squeeze(-1)
            offsets[c] = local.median(dim=0).values
    offsets[0] = 0.0
    return offsets


def end_site_offsets(offsets: torch.Tensor) -> dict[int, torch.Tensor]:
    """End Sites continue each leaf bone by half its length (they only shape the bones on screen)."""
    return {j: 0.5 * offsets[j] for j in range(sk.NUM_JOINTS) if not CHILDREN[j]}


def local_rotations(joints: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """(T, 22, 3, 3) local rotations that pose the rest skeleton onto the joint positions
    (see rigid_pose)."""
    return rigid_pose(joints, offsets)[0]


def rigid_joints(joints) -> np.ndarray:
    """The motion on a rigid skeleton with its own median bone lengths: exactly the joints its
    BVH holds. Bones keep their direction, as local_rotations aims them; a generated motion
    whose bones stretch from frame to frame loses the stretch, a recorded one stays as it is."""
    j = torch.as_tensor(np.asarray(joints, dtype=np.float64))
    return rigid_positions(j, rest_offsets(j)).numpy().astype(np.asarray(joints).dtype, copy=False)


def rigid_positions(joints: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """rigid_pose's joint positions without its rotations, several times faster (the foot clean-up
    runs on every generated motion). A single-child bone aimed by the shortest arc ends at its rest
    length along the motion's bone direction, whatever its parents' rotations; only the fitted
    frames of multi-child joints, and bones of zero length (which keep the parent's rotation),
    need rotations, and for the latter this falls back to rigid_pose."""
    placed: list[torch.Tensor | None] = [None] * sk.NUM_JOINTS
    placed[0] = joints[:, 0]
    lengths = offsets.norm(dim=-1)
    for j in range(sk.NUM_JOINTS):
        kids = CHILDREN[j]
        if j in FRAME_CHILDREN:
            world = _kabsch(offsets[list(kids)], joints[:, list(kids)] - placed[j].unsqueeze(1))
            for c in kids:
                placed[c] = placed[j] + (world @ offsets[c]).squeeze(-1)
        elif kids:
            (c,) = kids
            bone = joints[:, c] - placed[j]
            norm = bone.norm(dim=-1, keepdim=True)
            if bool((norm < 1e-9).any()):
                return rigid_pose(joints, offsets)[1]
            placed[c] = placed[j] + bone * (lengths[c] / norm)
    return torch.stack(placed, dim=1)


def rigid_pose(joints: torch.Tensor, offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, 22, 3, 3) local rotations that pose the rest skeleton onto the joint positions, and
    the (T, 22, 3) joint positions of that posed rest skeleton.

    Each bone is aimed from where the rest skeleton has put its joint so far towards the
    motion's child joint: a bone whose length differs from its rest length in some frame
    then misplaces only its own child, instead of shifting everything below it as aiming
    along the motion's bone direction would.
    """
    T = joints.shape[0]
    eye = torch.eye(3, dtype=joints.dtype).expand(T, 3, 3)
    world: list[torch.Tensor | None] = [None] * sk.NUM_JOINTS
    local: list[torch.Tensor | None] = [None] * sk.NUM_JOINTS
    placed: list[torch.Tensor | None] = [None] * sk.NUM_JOINTS
    placed[0] = joints[:, 0]
    for j in range(sk.NUM_JOINTS):  # parents precede children in JOINT_NAMES order
        p = int(sk.PARENTS[j])
        parent_world = eye if p < 0 else world[p]
        kids = CHILDREN[j]
        if j in FRAME_CHILDREN:
            actual = joints[:, list(kids)] - placed[j].unsqueeze(1)
            world[j] = _kabsch(offsets[list(kids)], actual)
            local[j] = parent_world.transpose(-1, -2) @ world[j]
        elif kids:
            (c,) = kids
            bone = joints[:, c] - placed[j]
            # Shortest arc in the parent's frame: the bone carries no twist of its own.
            in_parent = (parent_world.transpose(-1, -2) @ bone.unsqueeze(-1)).squeeze(-1)
            rot = quat_to_matrix(qbetween(offsets[c].expand_as(in_parent), in_parent))
            degenerate = bone.norm(dim=-1) < 1e-9
            local[j] = torch.where(degenerate[:, None, None], eye, rot)
            world[j] = parent_world @ local[j]
        else:
            local[j] = eye
            world[j] = parent_world
        for c in kids:
            placed[c] = placed[j] + (world[j] @ offsets[c].expand(T, 3).unsqueeze(-1)).squeeze(-1)
    return torch.stack(local, dim=1), torch.stack(placed, dim=1)


def _dfs_order() -> list[int]:
    order, stack = [], [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(CHILDREN[j]))
    return order


def _write_joint(lines: list[str], jt: int, depth: int, offsets, ends) -> None:
    ind = "\t" * depth
    rot_channels = " ".join(f"{a}rotation" for a in EULER_ORDERS[jt])
    if depth == 0:
        head, channels = "ROOT", f"CHANNELS 6 Xposition Yposition Zposition {rot_channels}"
    else:
        head, channels = "JOINT", f"CHANNELS 3 {rot_channels}"
    lines += [f"{ind}{head} {sk.JOINT_NAMES[jt]}", f"{ind}{{",
              f"{ind}\tOFFSET {_fmt(offsets[jt])}", f"{ind}\t{channels}"]
    for c in CHILDREN[jt]:
        _write_joint(lines, c, depth + 1, offsets, ends)
    if jt in ends:
        lines += [f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {_fmt(ends[jt])}", f"{ind}\t}}"]
    lines.append(f"{ind}}}")


def _fmt(v) -> str:
    return " ".join(f"{float(x):.6f}" for x in v)


def units_per_metre(units: str) -> float:
    """File units per metre for a `units` name; ValueError naming the choices otherwise."""
    if not isinstance(units, str) or units not in UNITS_PER_METRE:
        raise ValueError(f"BVH units must be one of {', '.join(map(repr, UNITS_PER_METRE))}, got {units!r}")
    return UNITS_PER_METRE[units]


def bvh_text(joints, fps: float = 20.0, units: str = DEFAULT_UNITS) -> str:
    """BVH text in `units` ("cm" or "m") for joints (T, 22, 3) in metres at `fps`."""
    scale = units_per_metre(units)
    j = _validated(joints, fps)
    t = torch.from_numpy(j)
    offsets = rest_offsets(t)
    rots = local_rotations(t, offsets)
    offsets = offsets * scale
    ends = end_site_offsets(offsets)

    lines = ["HIERARCHY"]
    _write_joint(lines, 0, 0, offsets, ends)
    order = _dfs_order()
    columns = [t[:, 0] * scale]
    for jt in order:
        euler = matrix_to_euler(rots[:, jt], EULER_ORDERS[jt])
        columns.append(torch.rad2deg(euler))
    motion = torch.cat(columns, dim=-1).numpy()
    # Euler angles are defined modulo 360 degrees: keep each channel continuous in time.
    motion[:, 3:] = np.unwrap(motion[:, 3:], period=360.0, axis=0)
    lines += ["MOTION", f"Frames: {j.shape[0]}", f"Frame Time: {1.0 / float(fps):.9f}"]
    body = "\n".join(" ".join(row) for row in np.char.mod("%.6f", motion))
    return "\n".join(lines) + "\n" + body + "\n"


def _validated(joints, fps: float) -> np.ndarray:
    if isinstance(joints, torch.Tensor):
        joints = joints.detach().cpu().numpy()
    j = np.asarray(joints)
    if j.ndim != 3 or j.shape[1:] != (sk.NUM_JOINTS, 3):
        raise BvhError(f"joints must have shape (T, 22, 3), got {j.shape}")
    if j.shape[0] < 1:
        raise BvhError("joints have zero frames")
    if not np.issubdtype(j.dtype, np.number) or not np.isfinite(j).all():
        raise BvhError("joints must be finite numbers")
    if not (isinstance(fps, numbers.Real) and not isinstance(fps, bool) and math.isfinite(fps) and fps > 0):
        raise BvhError(f"fps must be a positive number, got {fps!r}")
    return j.astype(np.float64)


def save_bvh(path: str | os.PathLike, joints, fps: float = 20.0, units: str = DEFAULT_UNITS) -> None:
    """Write joints (T, 22, 3) in metres at `fps` as a BVH file in `units` ("cm" or "m"), atomically."""
    path = Path(path)
    try:
        text = bvh_text(joints, fps, units)
    except BvhError as e:
        raise BvhError(f"{path}: {e}") from None
    if not path.parent.is_dir():
        raise BvhError(f"{path}: folder {path.parent} does not exist")
    atomic_write_text(path, text)
