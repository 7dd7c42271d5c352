"""A follow camera: fixed 3/4 viewing direction, target glides after the root, fixed zoom.

The direction is set once from the character's initial facing, so turns read as
turns, and the zoom is fixed for the clip, so nothing "breathes". Everything is
vectorised over frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from salad.motion import skeleton as sk

AZIMUTH_DEG = 35.0      # from the character's front towards its left
ELEVATION_DEG = 16.0    # looking slightly down: the floor reads, the body is not foreshortened
YFOV_DEG = 38.0         # a moderate telephoto, like a real camera at 4-6 m
FOLLOW_SIGMA_S = 0.6    # time constant of the follow, in seconds
MIN_RADIUS = 1.05       # never zoom in past a standing adult's half height plus margin
MARGIN = 1.12
DISTANCE_STEP = 0.2     # metres; the zoom snaps outwards to these steps


@dataclass(frozen=True)
class CameraPath:
    """Per-frame camera poses (camera-to-world, OpenGL convention) and projection."""

    poses: np.ndarray     # (T, 4, 4)
    targets: np.ndarray   # (T, 3)
    yfov: float           # radians
    aspect: float         # width / height

    @property
    def eyes(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def right_up_back(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera axes in world space, (T, 3) each; 'back' points from the scene to the camera."""
        return self.poses[:, :3, 0], self.poses[:, :3, 1], self.poses[:, :3, 2]

    def project(self, points: np.ndarray, width: int, height: int) -> np.ndarray:
        """Pixel coordinates (x right, y down) and depth of world points (T, N, 3) -> (T, N, 3)."""
        rel = points - self.eyes[:, None, :]
        rot = self.poses[:, :3, :3]
        cam = np.einsum("tnk,tkc->tnc", rel, rot)  # world -> camera coordinates
        depth = -cam[..., 2]
        f = 0.5 * height / np.tan(0.5 * self.yfov)
        x = width / 2 + f * cam[..., 0] / np.maximum(depth, 1e-9)
        y = height / 2 - f * cam[..., 1] / np.maximum(depth, 1e-9)
        return np.stack([x, y, depth], axis=-1)


def initial_facing(joints: np.ndarray) -> np.ndarray:
    """Unit XZ facing direction of frame 0, from hips and shoulders."""
    r_hip, l_hip, r_sh, l_sh = sk.FACE_JOINTS
    across = (joints[0, r_hip] - joints[0, l_hip]) + (joints[0, r_sh] - joints[0, l_sh])
    fwd = np.cross(np.array([0.0, 1.0, 0.0]), across)
    fwd[1] = 0.0
    n = np.linalg.norm(fwd)
    return fwd / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])


def look_at(eyes: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(T, 4, 4) camera-to-world poses looking from eyes at targets with +Y up."""
    back = eyes - targets
    back /= np.linalg.norm(back, axis=-1, keepdims=True)
    right = np.cross(np.array([0.0, 1.0, 0.0]), back)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    up = np.cross(back, right)
    poses = np.zeros((len(eyes), 4, 4))
    poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2], poses[:, :3, 3] = right, up, back, eyes
    poses[:, 3, 3] = 1.0
    return poses


def smooth_targets(joints: np.ndarray, fps: float) -> np.ndarray:
    """Where the camera looks each frame: the root's ground position and the body's
    vertical middle, both low-pass filtered so steps and bobbing do not shake the view."""
    sigma = FOLLOW_SIGMA_S * fps
    root = joints[:, 0, :].astype(np.float64)
    mid_y = 0.5 * (joints[..., 1].max(axis=1) + joints[..., 1].min(axis=1))
    target = np.stack([root[:, 0], mid_y, root[:, 2]], axis=-1)
    if len(target) > 1:
        target = gaussian_filter1d(target, sigma, axis=0, mode="nearest")
        # The vertical target moves less than the ground one: a jump should rise in frame.
        target[:, 1] = gaussian_filter1d(mid_y, 2.5 * sigma, mode="nearest")
    return target


def follow_camera(motions: list[np.ndarray], fps: float, aspect: float = 1.0,
                  facing: np.ndarray | None = None) -> list[CameraPath]:
    """One camera path per motion, sharing direction and zoom so panels compare 1:1."""
    facing = initial_facing(motions[0]) if facing is None else facing
    left = np.cross(np.array([0.0, 1.0, 0.0]), facing)  # character's left for a +Y up, +Z forward frame
    az, el = np.radians(AZIMUTH_DEG), np.radians(ELEVATION_DEG)
    horiz = np.cos(az) * facing + np.sin(az) * left
    view_dir = np.cos(el) * horiz + np.array([0.0, np.sin(el), 0.0])  # from target to eye
    yfov = np.radians(YFOV_DEG)
    tan_v = np.tan(yfov / 2)
    tan_h = tan_v * aspect
    right = np.cross(np.array([0.0, 1.0, 0.0]), view_dir)
    right /= np.linalg.norm(right)
    cam_up = np.cross(view_dir, right)

    targets = [smooth_targets(m, fps) for m in motions]
    # A point `along` metres towards the camera and (x, y) off the line of sight stays in
    # frame when |x| <= (distance - along) tan_h and |y| <= (distance - along) tan_v.
    distance = MIN_RADIUS / tan_v
    for m, t in zip(motions, targets):
        offsets = m - t[:, None, :]
        along = offsets @ view_dir
        need = np.maximum(np.abs(offsets @ right) / tan_h, np.abs(offsets @ cam_up) / tan_v)
        distance = max(distance, float((MARGIN * need + along).max()))
    # Snapping keeps the camera (and so a rendered panel, see video.PanelCache) identical when
    # a motion shown beside it changes a little, e.g. from one edit of a source to the next.
    distance = float(np.ceil(distance / DISTANCE_STEP - 1e-9) * DISTANCE_STEP)
    return [CameraPath(poses=look_at(t + distance * view_dir, t), targets=t, yfov=yfov,
                       aspect=aspect) for t in targets]
