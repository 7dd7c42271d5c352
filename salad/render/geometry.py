"""Vertex data for the skeleton, its floor shadow, target markers and the floor.

Each kind of object is one unit template (sphere, tube, flat stadium) instanced by
NumPy over all joints/bones and a block of frames at once, so the GPU gets a single
vertex buffer per object kind and frame: [x, y, z, r, g, b, a] float32 rows.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from salad.motion import skeleton as sk

import salad.render.style as style

UP = np.array([0.0, 1.0, 0.0])
BONES = tuple((int(p), c) for c, p in enumerate(sk.PARENTS) if p >= 0)
HEAD = sk.JOINT_NAMES.index("head")
HEAD_STRETCH = np.array([1.0, 1.13, 1.0])  # heads are taller than wide
_PARK = np.array([0.0, -50.0, 0.0])        # where unused instances collapse to a point


# ------------------------------------------------------------------ unit templates

@dataclass(frozen=True)
class Template:
    offsets: np.ndarray   # (n, 3) or (n, 2): unit directions in the instance's frame
    faces: np.ndarray     # (f, 3) int32, counter-clockwise seen from outside
    end: np.ndarray       # (n,) 0/1: which end point a vertex hangs off (tubes, stadiums)
    ring: np.ndarray      # (n,) 0 inner / 1 outer (stadiums)

    @property
    def n(self) -> int:
        return len(self.offsets)


def sphere_template(subdivisions: int) -> Template:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(m.vertices, dtype=np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    zeros = np.zeros(len(v), dtype=np.int64)
    return Template(v, np.asarray(m.faces, dtype=np.int32), zeros, zeros)


def tube_template(segments: int) -> Template:
    """Open cylinder between end 0 and end 1; offsets are (cos, sin) around the axis."""
    ang = 2 * np.pi * np.arange(segments) / segments
    circ = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    k = np.arange(segments)
    a0, a1 = k, (k + 1) % segments
    b0, b1 = a0 + segments, a1 + segments
    faces = np.concatenate([np.stack([a0, a1, b0], 1), np.stack([a1, b1, b0], 1)]).astype(np.int32)
    end = np.repeat([0, 1], segments)
    return Template(np.tile(circ, (2, 1)), faces, end, np.zeros(2 * segments, dtype=np.int64))


def stadium_template(cap_segments: int) -> Template:
    """Flat rounded strip from end 0 to end 1 on the floor with a solid core (ring 0) and a
    soft fringe that fades to nothing (ring 1); offsets are (along, across) units."""
    ang1 = np.linspace(-np.pi / 2, np.pi / 2, cap_segments + 1)   # end 1 cap
    ang0 = ang1 + np.pi                                             # end 0 cap
    ang = np.concatenate([ang1, ang0])
    k = len(ang)
    ring_xy = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    end = np.concatenate([np.ones(cap_segments + 1), np.zeros(cap_segments + 1)]).astype(np.int64)
    inner = np.arange(k)
    outer = inner + k
    nxt = (inner + 1) % k
    core = np.stack([np.zeros(k - 2, dtype=np.int64), inner[1:-1], inner[2:]], 1)
    fringe = np.concatenate([np.stack([inner, outer, outer[nxt]], 1),
                             np.stack([inner, outer[nxt], inner[nxt]], 1)])
    faces = np.concatenate([core, fringe]).astype(np.int32)
    return Template(np.tile(ring_xy, (2, 1)), faces, np.tile(end, 2), np.repeat([0, 1], k))


def _concat_faces(templates_counts: list[tuple[Template, int]]) -> np.ndarray:
    out, base = [], 0
    for tpl, count in templates_counts:
        offs = base + tpl.n * np.arange(count)
        out.append((tpl.faces[None, :, :] + offs[:, None, None]).reshape(-1, 3))
        base += tpl.n * count
    return np.concatenate(out).astype(np.int32) if out else np.zeros((0, 3), np.int32)


# ------------------------------------------------------------------ instancing

def _unit(v: np.ndarray, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = n > 1e-8
    return np.where(ok, v / np.where(ok, n, 1.0), fallback), n[..., 0]


def tube_frame(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors u, v perpendicular to the a->b axis with u x v along the axis."""
    d, _ = _unit(b - a, UP)
    ref = np.where(np.abs(d[..., 1:2]) < 0.9, UP, np.array([1.0, 0.0, 0.0]))
    u, _ = _unit(np.cross(d, ref), np.array([1.0, 0.0, 0.0]))
    return u, np.cross(d, u)


def spheres(tpl: Template, centres: np.ndarray, radii: np.ndarray,
            stretch: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Positions and normals of spheres: centres (..., k, 3), radii (k,) -> (..., k, n, 3)."""
    shape = tpl.offsets if stretch is None else tpl.offsets * stretch
    pos = centres[..., None, :] + radii[:, None, None] * shape
    nrm = np.broadcast_to(tpl.offsets, pos.shape)
    return pos, nrm


def tubes(tpl: Template, a: np.ndarray, b: np.ndarray, ra: np.ndarray, rb: np.ndarray):
    """Positions and normals of tubes a->b with end radii; a, b (..., k, 3) -> (..., k, n, 3)."""
    u, v = tube_frame(a, b)
    nrm = tpl.offsets[:, 0, None] * u[..., None, :] + tpl.offsets[:, 1, None] * v[..., None, :]
    at_b = tpl.end.astype(bool)[:, None]
    base = np.where(at_b, b[..., None, :], a[..., None, :])
    r = np.where(tpl.end.astype(bool), np.broadcast_to(rb, a.shape[:-1])[..., None],
                 np.broadcast_to(ra, a.shape[:-1])[..., None])
    return base + r[..., None] * nrm, nrm


def pack(pos: np.ndarray, rgb: np.ndarray, alpha: np.ndarray | float = 1.0) -> np.ndarray:
    """(..., n, 3) positions and colours -> (..., n, 7) float32 rows."""
    out = np.empty(pos.shape[:-1] + (7,), dtype=np.float32)
    out[..., :3] = pos
    out[..., 3:6] = rgb
    out[..., 6] = alpha
    return out


# ------------------------------------------------------------------ the skeleton

def body_scale(joints: np.ndarray) -> float:
    """Size of the figure relative to a 1.7 m adult, from median bone lengths."""
    chain = [(0, 3), (3, 6), (6, 9), (9, 12), (12, 15), (0, 1), (1, 4), (4, 7)]
    lengths = np.median(np.stack([np.linalg.norm(joints[:, c] - joints[:, p], axis=-1)
                                  for p, c in chain]), axis=1)
    height = lengths[:5].sum() + lengths[6:].sum() + 0.2  # neck-to-crown and heel pad
    return float(np.clip(height / style.REFERENCE_HEIGHT, 0.4, 2.5))


class SkeletonGeometry:
    """Joint spheres + bone tubes + soft floor shadows for any block of frames."""

    def __init__(self, scale: float = 1.0):
        # Joint spheres are 4-8 px across at video sizes: 42 vertices are plenty, and
        # every vertex costs the software rasteriser time. The head is big enough for more.
        self.joint_tpl = sphere_template(1)
        self.head_tpl = sphere_template(2)
        self.bone_tpl = tube_template(12)
        self.shadow_tpl = stadium_template(6)
        self.scale = scale
        self.joint_radius = np.full(sk.NUM_JOINTS, style.JOINT_RADIUS * scale)
        self.joint_radius[HEAD] = style.HEAD_RADIUS * scale
        self.bone_radius = np.array([
            (style.BONE_RADIUS_TRUNK if bone in style.TRUNK_BONES else style.BONE_RADIUS_LIMB) * scale
            for bone in BONES])
        self.parents = np.array([p for p, _ in BONES])
        self.children = np.array([c for _, c in BONES])
        self.small = np.array([j for j in range(sk.NUM_JOINTS) if j != HEAD])
        self.faces = _concat_faces([(self.joint_tpl, len(self.small)), (self.head_tpl, 1),
                                    (self.bone_tpl, len(BONES))])
        self.shadow_faces = _concat_faces([(self.shadow_tpl, len(BONES) + 1)])
        self.n_vertices = self.joint_tpl.n * len(self.small) + self.head_tpl.n + self.bone_tpl.n * len(BONES)
        self.n_shadow_vertices = self.shadow_tpl.n * (len(BONES) + 1)

    def body(self, joints: np.ndarray, albedo: np.ndarray, lights, view: np.ndarray) -> np.ndarray:
        """Lit vertex rows (t, V, 7) for joints (t, 22, 3) with per-joint sRGB albedo: (t, 22, 3),
        or (1, 22, 3) when colours do not change over time (then sphere colours are shaded once)."""
        t = len(joints)
        sp, sn = spheres(self.joint_tpl, joints[:, self.small], self.joint_radius[self.small])
        hp, hn = spheres(self.head_tpl, joints[:, [HEAD]], self.joint_radius[[HEAD]], HEAD_STRETCH)
        a, b = joints[:, self.parents], joints[:, self.children]
        bp, bn = tubes(self.bone_tpl, a, b, self.bone_radius, self.bone_radius * 0.85)
        # Sphere normals do not turn with the motion, so their shading only changes with albedo.
        s_rgb = style.shade(albedo[:, self.small, None, :], sn[:1], view, lights)
        h_rgb = style.shade(albedo[:, [HEAD], None, :], hn[:1], view, lights)
        b_rgb = style.shade(albedo[:, self.children, None, :], bn, view, lights)
        return np.concatenate([pack(sp, np.broadcast_to(s_rgb, sp.shape)).reshape(t, -1, 7),
                               pack(hp, np.broadcast_to(h_rgb, hp.shape)).reshape(t, -1, 7),
                               pack(bp, b_rgb).reshape(t, -1, 7)], axis=1)

    def shadow(self, joints: np.ndarray, light_dir: np.ndarray) -> np.ndarray:
        """Soft floor shadows (t, V, 7) cast along -light_dir; blur grows and opacity falls
        with height, so planted feet get crisp dark contacts and a jump a faint haze."""
        a = joints[:, list(self.parents) + [HEAD]]
        b = joints[:, list(self.children) + [HEAD]]
        ra = np.concatenate([self.joint_radius[self.parents], [self.joint_radius[HEAD]]])
        rb = np.concatenate([self.joint_radius[self.children], [self.joint_radius[HEAD]]])
        ha, hb = np.clip(a[..., 1], 0.0, None), np.clip(b[..., 1], 0.0, None)
        lift = light_dir / max(light_dir[1], 0.2)
        fa = a - ha[..., None] * lift
        fb = b - hb[..., None] * lift
        along, _ = _unit((fb - fa) * np.array([1.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
        across = np.cross(UP, along)
        tpl = self.shadow_tpl
        at_b = tpl.end.astype(bool)
        base = np.where(at_b[:, None], fb[..., None, :], fa[..., None, :])
        h = np.where(at_b, hb[..., None], ha[..., None])
        r_core = np.where(at_b, rb[:, None], ra[:, None]) * 1.1
        blur = (0.02 + 0.14 * h) * self.scale
        radius = r_core + tpl.ring * blur
        off = tpl.offsets[:, 0, None] * along[..., None, :] + tpl.offsets[:, 1, None] * across[..., None, :]
        pos = base + radius[..., None] * off
        # Each strip sits a hair above the previous one so overlapping strips blend
        # instead of fighting in the depth buffer.
        pos[..., 1] = 0.0015 + 0.0004 * np.arange(len(ra))[:, None]
        alpha = style.SHADOW_OPACITY * np.exp(-h / (style.SHADOW_FALLOFF * self.scale)) * (1 - tpl.ring)
        rgb = np.broadcast_to(style.SHADOW_COLOR, pos.shape)
        return pack(pos, rgb, alpha).reshape(len(joints), -1, 7)


# ------------------------------------------------------------------ markers

class TargetGeometry:
    """Targets: every constrained (frame, joint) as a small static dot, the current
    frame's targets as larger markers joined to their joints by thin lines."""

    def __init__(self, targets: np.ndarray, mask: np.ndarray, scale: float, max_static: int = 600):
        self.targets, self.mask, self.scale = targets, mask, scale
        self.dot_tpl = sphere_template(1)
        self.line_tpl = tube_template(6)
        self.capacity = int(mask.sum(axis=1).max()) if mask.size else 0
        t_idx, j_idx = np.nonzero(mask)
        if len(t_idx) > max_static:  # a full-body, every-frame constraint would be a cloud
            keep = np.linspace(0, len(t_idx) - 1, max_static).round().astype(int)
            t_idx, j_idx = t_idx[keep], j_idx[keep]
        self.static_points = targets[t_idx, j_idx]
        self.static_faces = _concat_faces([(self.dot_tpl, len(self.static_points))])
        self.dynamic_faces = _concat_faces([(self.dot_tpl, self.capacity), (self.line_tpl, self.capacity)])
        self.n_dynamic_vertices = (self.dot_tpl.n + self.line_tpl.n) * self.capacity

    def static(self, lights, view) -> np.ndarray:
        pos, nrm = spheres(self.dot_tpl, self.static_points, np.full(len(self.static_points),
                                                                      style.TARGET_RADIUS * self.scale))
        rgb = style.shade(np.broadcast_to(style.TARGET_COLOR, pos.shape), nrm, view, lights)
        return pack(pos, rgb, 1.0).reshape(-1, 7)

    def dynamic(self, frames: slice, joints: np.ndarray, lights, view) -> np.ndarray:
        """(t, V, 7) for the current-frame markers of `frames`; unused slots collapse."""
        mask = self.mask[frames]
        t = len(mask)
        k = self.capacity
        order = np.argsort(~mask, axis=1, kind="stable")[:, :k]
        valid = np.take_along_axis(mask, order, axis=1)
        tgt = np.take_along_axis(self.targets[frames], order[..., None], axis=1)
        cur = np.take_along_axis(joints, order[..., None], axis=1)
        tgt = np.where(valid[..., None], tgt, _PARK)
        cur = np.where(valid[..., None], cur, _PARK)
        dp, dn = spheres(self.dot_tpl, tgt, np.full(k, style.TARGET_ACTIVE_RADIUS * self.scale))
        dp = np.where(valid[..., None, None], dp, _PARK)
        r_line = np.full(k, style.CONNECTOR_RADIUS * self.scale)
        lp, ln = tubes(self.line_tpl, cur, tgt, r_line, r_line)
        lp = np.where(valid[..., None, None], lp, _PARK)
        d_rgb = style.shade(np.broadcast_to(style.TARGET_ACTIVE_COLOR, dp.shape), dn, view, lights)
        l_rgb = style.shade(np.broadcast_to(style.TARGET_ACTIVE_COLOR, lp.shape), ln, view, lights)
        return np.concatenate([pack(dp, d_rgb).reshape(t, -1, 7), pack(lp, l_rgb).reshape(t, -1, 7)], 1)


def path_ribbon(path: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat band on the floor along a polyline (n, 3): vertex rows and faces."""
    p = path[:, [0, 2]].astype(np.float64)
    seg = np.diff(p, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    keep = np.concatenate([[True], seg_len > 1e-4])
    p = p[keep]
    if len(p) < 2:
        return np.zeros((0, 7), np.float32), np.zeros((0, 3), np.int32)
    tang = np.gradient(p, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
    left, right = p + 0.5 * width * normal, p - 0.5 * width * normal
    pts2 = np.stack([left, right], axis=1).reshape(-1, 2)
    pos = np.stack([pts2[:, 0], np.full(len(pts2), 0.0012), pts2[:, 1]], axis=1)
    n = len(p)
    i = 2 * np.arange(n - 1)
    # Seen from above (+Y) with x right and z down the page, (l0, l1, r0) winds counter-clockwise.
    faces = np.concatenate([np.stack([i, i + 2, i + 1], 1), np.stack([i + 1, i + 2, i + 3], 1)])
    return pack(pos, np.broadcast_to(style.PATH_COLOR, pos.shape), 0.85), faces.astype(np.int32)


# ------------------------------------------------------------------ the floor

def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def floor_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A round checker floor centred on the origin that fades into the background."""
    tile, radius = style.FLOOR_TILE, style.FLOOR_RADIUS
    n = int(np.ceil(radius / tile))
    ix, iz = np.meshgrid(np.arange(-n, n), np.arange(-n, n), indexing="ij")
    ix, iz = ix.ravel(), iz.ravel()
    centre = (np.stack([ix, iz], 1) + 0.5) * tile
    inside = np.linalg.norm(centre, axis=1) < radius + tile
    ix, iz = ix[inside], iz[inside]
    corners = np.array([[0, 0], [0, 1], [1, 1], [1, 0]])  # counter-clockwise seen from +Y
    xz = (np.stack([ix, iz], 1)[:, None, :] + corners[None]) * tile
    dark = ((ix + iz) % 2 == 0)[:, None, None]
    dist = np.linalg.norm(xz, axis=-1)
    mean = (style.FLOOR_DARK + style.FLOOR_LIGHT) / 2
    contrast = 1.0 - _smoothstep((dist - style.FLOOR_CONTRAST_START)
                                 / (style.FLOOR_CONTRAST_END - style.FLOOR_CONTRAST_START))
    base = mean + (np.where(dark, style.FLOOR_DARK, style.FLOOR_LIGHT) - mean) * contrast[..., None]
    start = style.FLOOR_FADE_START * radius
    fade = _smoothstep((dist - start) / (radius - start))
    rgb = base * (1 - fade[..., None]) + style.BACKGROUND * fade[..., None]
    pos = np.stack([xz[..., 0], np.zeros_like(dist), xz[..., 1]], axis=-1)
    q = 4 * np.arange(len(ix))
    faces = np.concatenate([np.stack([q, q + 1, q + 2], 1), np.stack([q, q + 2, q + 3], 1)])
    return pack(pos, rgb).reshape(-1, 7), faces.astype(np.int32)
