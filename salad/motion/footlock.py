"""Foot locking: feet that the model says are on the floor stay where they landed.

A latent diffusion model gets the rough gait right but lets planted feet drift by a few
centimetres a frame, which reads as skating. The decoder also predicts four foot-contact
channels (left ankle, left toe, right ankle, right toe); where they say a foot is planted,
and the foot is near the floor, its ankle is pinned to one spot for the whole contact, the
leg is re-solved with two-bone IK (hip fixed, knee kept in the leg's own bending plane, bone
lengths kept), and the toe follows the ankle. The correction fades in and out over a few
frames on each side of a contact, so the foot never jumps.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d, uniform_filter1d

from . import skeleton as sk

CONTACT_PROB = 0.5        # a contact channel above this means "planted"
NEAR_FLOOR_M = 0.06       # a foot planted higher than this above the motion's floor is in the air
BLEND_FRAMES = 4          # frames over which the correction fades in and out (0.2 s at 20 fps)
MIN_CONTACT_FRAMES = 2    # a single-frame contact is noise, not a footstep
# The contact channels mark a foot moving under ~0.9 m/s (HumanML3D's rule), which includes the
# landing and lift-off; pinning those frames too would stretch the leg. A footstep is the run of
# frames around the foot's slowest moment that stays within this distance of where it was then.
MAX_PIN_DRIFT_M = 0.20
REACH = 0.995             # of the leg's length: a knee locked fully straight looks stiff
KNEE_FORWARD_BIAS_M = 0.05
MAX_PELVIS_DROP_M = 0.06  # lowering the body more than this reads as a crouch; the foot gives way instead

# (hip, knee, ankle, toe) of each leg, and the contact channels (indices into the four) of each foot
LEGS = {
    "left": (sk.JOINT_NAMES.index("left_hip"), sk.JOINT_NAMES.index("left_knee"),
             sk.FOOT_JOINTS_LEFT[0], sk.FOOT_JOINTS_LEFT[1]),
    "right": (sk.JOINT_NAMES.index("right_hip"), sk.JOINT_NAMES.index("right_knee"),
              sk.FOOT_JOINTS_RIGHT[0], sk.FOOT_JOINTS_RIGHT[1]),
}
CONTACT_CHANNELS = {"left": (0, 1), "right": (2, 3)}


@dataclass
class FootLockReport:
    frames_locked: dict[str, int]     # per foot, frames pinned to a footstep
    footsteps: dict[str, int]         # per foot, contact segments
    max_shift_m: float                # largest ankle displacement the lock made
    unreachable_frames: int           # frames where the leg could not reach the pinned spot
    max_pelvis_drop_m: float = 0.0    # how far the body was lowered so a leg could reach

    def as_dict(self) -> dict:
        return {"frames_locked": dict(self.frames_locked), "footsteps": dict(self.footsteps),
                "max_shift_m": round(self.max_shift_m, 4), "unreachable_frames": self.unreachable_frames,
                "max_pelvis_drop_m": round(self.max_pelvis_drop_m, 4)}


def contact_segments(planted: np.ndarray, min_len: int = MIN_CONTACT_FRAMES) -> list[tuple[int, int]]:
    """[start, end) runs of True in a (T,) bool array, at least min_len long."""
    edges = np.diff(np.concatenate(([0], planted.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(s), int(e)) for s, e in zip(starts, ends) if e - s >= min_len]


def planted_frames(joints: np.ndarray, contacts: np.ndarray, foot: str) -> np.ndarray:
    """(T,) bool: the decoder calls the foot planted and it is within NEAR_FLOOR_M of the floor.
    The floor is the motion's own (the lowest toe height over the clip), so a generated motion
    that hovers a little still locks its steps."""
    _, _, ankle, toe = LEGS[foot]
    prob = contacts[:, list(CONTACT_CHANNELS[foot])].max(axis=1)
    floor = joints[:, list(sk.CONTACT_JOINTS), 1].min()
    low = joints[:, toe, 1] - floor < NEAR_FLOOR_M
    low |= joints[:, ankle, 1] - joints[:, ankle, 1].min() < NEAR_FLOOR_M
    return (prob > CONTACT_PROB) & low


def planted_mask(joints: np.ndarray, contacts: np.ndarray) -> np.ndarray:
    """(T, 4) bool in skeleton.CONTACT_JOINTS order: planted_frames of each foot, for both of its joints."""
    return np.stack([planted_frames(joints, contacts, foot) for foot in LEGS for _ in CONTACT_CHANNELS[foot]],
                    axis=1)


def footsteps(point: np.ndarray, planted: np.ndarray, max_drift: float = MAX_PIN_DRIFT_M,
              min_len: int = MIN_CONTACT_FRAMES) -> list[tuple[int, int]]:
    """[start, end) footsteps: within each planted run, the frames around the point's slowest
    horizontal moment that stay within max_drift of it (horizontally)."""
    flat = point[:, [0, 2]]
    speed = np.r_[np.inf, np.linalg.norm(np.diff(flat, axis=0), axis=-1)]
    speed[0] = speed[1] if len(speed) > 1 else 0.0
    out = []
    for s, e in contact_segments(planted, min_len):
        k = s + int(np.argmin(speed[s:e]))
        near = np.linalg.norm(flat[s:e] - flat[k], axis=-1) <= max_drift
        a = k
        while a > s and near[a - 1 - s]:
            a -= 1
        b = k + 1
        while b < e and near[b - s]:
            b += 1
        if b - a >= min_len:
            out.append((a, b))
    return out


def _fade(distance: np.ndarray, width: int) -> np.ndarray:
    """1 at distance 0, smoothly down to 0 at `width` frames (smoothstep)."""
    x = np.clip(1.0 - distance / (width + 1.0), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def pin_offsets(point: np.ndarray, segments: list[tuple[int, int]], blend: int = BLEND_FRAMES) -> np.ndarray:
    """(T, 3) horizontal moves that hold `point` (T, 3) still during each footstep (at its mean
    position there; heights are left alone), fading to nothing over `blend` frames outside."""
    T = len(point)
    offset = np.zeros_like(point)
    weight = np.zeros(T)
    frames = np.arange(T)
    for s, e in segments:
        pin = point[s:e].mean(axis=0)
        inside = np.zeros(T, dtype=bool)
        inside[s:e] = True
        # Outside the contact the offset is the one at the nearer end, faded with distance;
        # of two neighbouring contacts, the nearer one's fade wins.
        dist = np.where(frames < s, s - frames, np.where(frames >= e, frames - (e - 1), 0))
        w = np.where(inside, 1.0, _fade(dist.astype(float), blend))
        end_offset = np.where((frames < s)[:, None], pin - point[s], pin - point[e - 1])
        seg_offset = np.where(inside[:, None], pin - point, end_offset)
        take = w > weight
        offset[take] = (seg_offset * w[:, None])[take]
        weight[take] = w[take]
    offset[:, 1] = 0.0
    return offset


def two_bone_ik(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, target: np.ndarray,
                forward: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Knee and ankle positions (T, 3) each that put the ankle at `target` with the hip fixed and
    both bone lengths kept; the knee bends the way the original leg bends, and towards `forward`
    (T, 3), the body's facing, where the original leg is nearly straight and says little. Where
    the target is out of reach the leg points at it as far as it can. Also returns the (T,) bool
    unreachable mask."""
    l1 = np.linalg.norm(knee - hip, axis=-1)
    l2 = np.linalg.norm(ankle - knee, axis=-1)
    to_target = target - hip
    d_want = np.linalg.norm(to_target, axis=-1)
    lo, hi = np.abs(l1 - l2) + 1e-4, l1 + l2 - 1e-4
    d = np.clip(d_want, lo, hi)
    unreachable = (d_want > hi + 1e-3) | (d_want < lo - 1e-3)
    axis = to_target / np.maximum(d_want, 1e-8)[:, None]
    # the knee's direction away from the hip-ankle line, taken from the original pose
    # A straight leg's knee lies on the hip-ankle line, and the side it leaves it by flips from
    # frame to frame; a few centimetres of bias towards the facing keep the bend steady.
    leg = ankle - hip
    leg = leg / np.maximum(np.linalg.norm(leg, axis=-1, keepdims=True), 1e-8)
    pole = (knee - hip) - ((knee - hip) * leg).sum(-1, keepdims=True) * leg      # the original leg's own bend
    if forward is not None:
        pole = pole + KNEE_FORWARD_BIAS_M * forward
    pole = pole - (pole * axis).sum(-1, keepdims=True) * axis
    pole_n = np.linalg.norm(pole, axis=-1, keepdims=True)
    fallback = np.cross(axis, np.array([1.0, 0.0, 0.0]))
    pole = np.where(pole_n > 1e-6, pole / np.maximum(pole_n, 1e-8), fallback)
    along = (l1 ** 2 - l2 ** 2 + d ** 2) / (2.0 * d)
    across = np.sqrt(np.maximum(l1 ** 2 - along ** 2, 0.0))
    new_knee = hip + axis * along[:, None] + pole * across[:, None]
    new_ankle = hip + axis * d[:, None]
    return new_knee, new_ankle, unreachable


def pelvis_drop(hip: np.ndarray, target: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(T,) how far the hip must come down (>= 0) for `target` to lie within `reach` of it.
    A stance leg is nearly straight, so a pinned foot a centimetre further away than the leg
    was is out of reach; lowering the body a little is what an animator would do."""
    v = target - hip
    flat2 = v[:, 0] ** 2 + v[:, 2] ** 2
    room = np.sqrt(np.maximum(reach ** 2 - flat2, 0.0))
    return np.maximum(0.0, -v[:, 1] - room)


def lock_feet(joints: np.ndarray, contacts: np.ndarray, blend: int = BLEND_FRAMES
              ) -> tuple[np.ndarray, FootLockReport]:
    """joints (T, 22, 3) metres, Y up; contacts (T, 4) contact probabilities (or 0/1) in
    skeleton.CONTACT_JOINTS order, e.g. the last four feature channels. Returns the locked
    joints (a new array) and what was done."""
    j = np.asarray(joints, dtype=np.float64)
    c = np.asarray(contacts, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"joints: expected shape (T, {sk.NUM_JOINTS}, 3), got {j.shape}")
    if c.shape != (len(j), 4):
        raise ValueError(f"contacts: expected shape ({len(j)}, 4), got {c.shape}")
    targets, locked, steps = {}, {}, {}
    for foot, (hip, knee, ankle, toe) in LEGS.items():
        # The toe is what stays put through a step (the heel lifts and the foot rolls over it),
        # so the toe is pinned and the ankle keeps its place relative to it.
        segments = footsteps(j[:, toe], planted_frames(j, c, foot))
        steps[foot] = len(segments)
        locked[foot] = int(sum(e - s for s, e in segments))
        targets[foot] = j[:, ankle] + pin_offsets(j[:, toe], segments, blend)
    if not any(steps.values()):
        return np.array(joints, copy=True), FootLockReport(locked, steps, 0.0, 0)

    # Lower the body where a pinned foot is out of the leg's reach, smoothly (a running maximum
    # keeps the needed drop, the moving average that follows keeps it from popping).
    drop = np.zeros(len(j))
    for foot, (hip, knee, ankle, _) in LEGS.items():
        reach = REACH * (np.linalg.norm(j[:, knee] - j[:, hip], axis=-1) +
                         np.linalg.norm(j[:, ankle] - j[:, knee], axis=-1))
        drop = np.maximum(drop, pelvis_drop(j[:, hip], targets[foot], reach))
    drop = np.minimum(drop, MAX_PELVIS_DROP_M)
    if drop.any():
        drop = uniform_filter1d(maximum_filter1d(drop, 2 * blend + 1, mode="nearest"), blend + 1, mode="nearest")
    body = j.copy()
    body[:, :, 1] -= drop[:, None]

    out = body.copy()
    unreachable, shift = 0, 0.0
    across = j[:, LEGS["left"][0]] - j[:, LEGS["right"][0]]
    forward = np.cross(across, np.array([0.0, 1.0, 0.0]))
    forward /= np.maximum(np.linalg.norm(forward, axis=-1, keepdims=True), 1e-8)
    for foot, (hip, knee, ankle, toe) in LEGS.items():
        new_knee, new_ankle, bad = two_bone_ik(body[:, hip], body[:, knee], body[:, ankle], targets[foot], forward)
        moved = new_ankle - j[:, ankle]
        out[:, knee], out[:, ankle] = new_knee, new_ankle
        out[:, toe] = j[:, toe] + moved
        unreachable += int(bad.sum())
        shift = max(shift, float(np.linalg.norm(moved, axis=-1).max()))
    report = FootLockReport(locked, steps, shift, unreachable, float(drop.max()))
    return out.astype(np.asarray(joints).dtype, copy=False), report


def lock_feet_features(joints: np.ndarray, features: np.ndarray, blend: int = BLEND_FRAMES
                       ) -> tuple[np.ndarray, FootLockReport]:
    """lock_feet with the contacts read from 263-d features (the last four channels)."""
    f = np.asarray(features)
    if f.ndim != 2 or f.shape[1] < 4 or len(f) != len(joints):
        raise ValueError(f"features: expected shape ({len(joints)}, 263), got {f.shape}")
    return lock_feet(joints, f[:, -4:], blend)
