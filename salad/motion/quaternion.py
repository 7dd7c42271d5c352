"""Quaternion and rotation helpers on torch tensors, (w, x, y, z) order, batched over leading dims."""
from __future__ import annotations

import torch


def qmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack((
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ), dim=-1)


def qinv(q: torch.Tensor) -> torch.Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def qrot(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    qvec = q[..., 1:]
    uv = torch.cross(qvec, v, dim=-1)
    uuv = torch.cross(qvec, uv, dim=-1)
    return v + 2.0 * (q[..., :1] * uv + uuv)


def qnormalize(q: torch.Tensor) -> torch.Tensor:
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def qbetween(v0: torch.Tensor, v1: torch.Tensor) -> torch.Tensor:
    """The shortest-arc rotation taking direction v0 onto direction v1."""
    v0, v1 = torch.broadcast_tensors(v0, v1)
    axis = torch.cross(v0, v1, dim=-1)
    w = (v0.norm(dim=-1) * v1.norm(dim=-1) + (v0 * v1).sum(-1)).unsqueeze(-1)
    q = torch.cat((w, axis), dim=-1)
    # Opposite directions have no unique shortest arc: turn 180 degrees about any
    # axis perpendicular to v0 instead of producing a zero quaternion.
    degenerate = q.norm(dim=-1, keepdim=True) < 1e-7 * (v0.norm(dim=-1, keepdim=True) ** 2 + 1e-12)
    if degenerate.any():
        helper = torch.where(
            v0[..., :1].abs() < 0.9, v0.new_tensor([1.0, 0.0, 0.0]), v0.new_tensor([0.0, 1.0, 0.0]))
        perp = torch.cross(v0, helper.expand_as(v0), dim=-1)
        q = torch.where(degenerate, torch.cat((torch.zeros_like(w), perp), dim=-1), q)
    return qnormalize(q)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = qnormalize(q).unbind(-1)
    return torch.stack((
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ), dim=-1).reshape(q.shape[:-1] + (3, 3))


def quat_to_cont6d(q: torch.Tensor) -> torch.Tensor:
    """The first two columns of the rotation matrix, concatenated (Zhou et al. 6D)."""
    m = quat_to_matrix(q)
    return torch.cat((m[..., 0], m[..., 1]), dim=-1)


def yaw_quat(angle: torch.Tensor) -> torch.Tensor:
    """Rotation about +Y by angle (radians)."""
    half = angle / 2
    zero = torch.zeros_like(half)
    return torch.stack((torch.cos(half), zero, torch.sin(half), zero), dim=-1)


def euler_to_matrix(angles: torch.Tensor, order: str) -> torch.Tensor:
    """Intrinsic Euler angles (radians, ..., 3, in `order`) to rotation matrices.

    BVH channels list rotations outermost first: "ZXY" means R = Rz @ Rx @ Ry.
    """
    mats = []
    for i, axis in enumerate(order.upper()):
        a = angles[..., i]
        c, s = torch.cos(a), torch.sin(a)
        one, zero = torch.ones_like(a), torch.zeros_like(a)
        if axis == "X":
            m = (one, zero, zero, zero, c, -s, zero, s, c)
        elif axis == "Y":
            m = (c, zero, s, zero, one, zero, -s, zero, c)
        elif axis == "Z":
            m = (c, -s, zero, s, c, zero, zero, zero, one)
        else:
            raise ValueError(f"unknown rotation axis {axis!r} in order {order!r}")
        mats.append(torch.stack(m, -1).reshape(a.shape + (3, 3)))
    out = mats[0]
    for m in mats[1:]:
        out = out @ m
    return out


def matrix_to_euler(m: torch.Tensor, order: str) -> torch.Tensor:
    """Inverse of euler_to_matrix for the Tait-Bryan orders (all three axes distinct)."""
    order = order.upper()
    idx = {"X": 0, "Y": 1, "Z": 2}
    i, j, k = (idx[a] for a in order)
    if len({i, j, k}) != 3:
        raise ValueError(f"only Tait-Bryan orders are supported, got {order!r}")
    # Parity of the permutation decides the signs below.
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    # R = R_i(a) R_j(b) R_k(c); element (i, k) = sign * sin(b).
    sb = (sign * m[..., i, k]).clamp(-1.0, 1.0)
    b = torch.asin(sb)
    a = torch.atan2(-sign * m[..., j, k], m[..., k, k])
    c = torch.atan2(-sign * m[..., i, j], m[..., i, i])
    # Gimbal lock: put all the rotation into the first angle.
    locked = sb.abs() > 1 - 1e-6
    if locked.any():
        a_locked = torch.atan2(sign * m[..., k, j], m[..., j, j])
        a = torch.where(locked, a_locked, a)
        c = torch.where(locked, torch.zeros_like(c), c)
    return torch.stack((a, b, c), dim=-1)
