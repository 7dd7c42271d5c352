"""Skeleton videos: single clips, synchronised side-by-side panels, GIFs and frame strips.

Frames are produced in blocks: vertex data for a block of frames is built by NumPy
in one go, then each frame is one buffer update + draw + read-back, and the encoder
(an ffmpeg subprocess fed through imageio) compresses in parallel on the other core.
Side-by-side panels are kept once drawn (PanelCache), so the unchanged source of a
series of edits is drawn only once.
"""
from __future__ import annotations

import hashlib
import os
import threading
import time
from collections import OrderedDict
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from salad.motion import skeleton as sk

import salad.render.camera as cam
import salad.render.geometry as geo
import salad.render.overlay as overlay
import salad.render.style as style
from .backend import gl_backend
from .engine import engine
from .workers import shares as worker_shares
from ..files import atomic_path
from ..progress import Progress

DEFAULT_SIZE = (448, 448)
PANEL_SIZE = (384, 384)
BLOCK = 24          # frames of vertex data built per NumPy pass
MAX_FRAMES = 20 * 60 * 10
X264_PRESET, X264_CRF = "ultrafast", 22   # encoding costs a third of superfast's; files ~1.5x larger
PANEL_CACHE_BYTES = 256 * 2**20   # finished side-by-side panels kept for reuse
_last_stats: dict = {}


# ------------------------------------------------------------------ validation

def _check_joints(joints, name: str = "joints") -> np.ndarray:
    arr = np.asarray(joints)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name}: expected a numeric array of shape (T, 22, 3), got dtype {arr.dtype}")
    if arr.ndim != 3 or arr.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"{name}: expected shape (T, {sk.NUM_JOINTS}, 3) in metres, got {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name}: the motion is empty (0 frames)")
    if arr.shape[0] > MAX_FRAMES:
        raise ValueError(f"{name}: {arr.shape[0]} frames is more than the {MAX_FRAMES} this renderer accepts")
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        t, j, _ = np.argwhere(bad)[0]
        raise ValueError(f"{name}: {int(bad.any(axis=(1, 2)).sum())} frame(s) contain NaN/inf "
                         f"(first at frame {t}, joint {j} {sk.JOINT_NAMES[j]})")
    if np.abs(arr).max() > 1e4:
        raise ValueError(f"{name}: coordinates up to {np.abs(arr).max():.3g}; expected metres (|x| < 1e4)")
    return arr


def _check_size(size) -> tuple[int, int]:
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size: expected (width, height) integers, got {size!r}") from None
    if not (32 <= w <= 4096 and 32 <= h <= 4096):
        raise ValueError(f"size: width and height must be in 32..4096, got {(w, h)}")
    return w + (w % 2), h + (h % 2)  # H.264 4:2:0 needs even sides


def _check_fps(fps) -> float:
    fps = float(fps)
    if not np.isfinite(fps) or not 1 <= fps <= 240:
        raise ValueError(f"fps: must be between 1 and 240, got {fps}")
    return fps


def _check_tint(tint, n_frames: int) -> np.ndarray | None:
    if tint is None:
        return None
    arr = np.asarray(tint, dtype=np.float64)
    if arr.shape != (n_frames, sk.NUM_JOINTS):
        raise ValueError(f"tint: expected shape ({n_frames}, {sk.NUM_JOINTS}) (frames x joints), "
                         f"got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("tint: contains NaN/inf")
    if arr.min() < -1e-6 or arr.max() > 1 + 1e-6:
        raise ValueError(f"tint: values must lie in [0, 1], got [{arr.min():.3g}, {arr.max():.3g}]")
    return np.clip(arr, 0.0, 1.0)


def _check_targets(targets, mask, n_frames: int) -> tuple[np.ndarray, np.ndarray] | None:
    if targets is None and mask is None:
        return None
    if targets is None or mask is None:
        raise ValueError("targets and target_mask must be given together")
    tg = np.asarray(targets, dtype=np.float64)
    mk = np.asarray(mask)
    if tg.shape != (n_frames, sk.NUM_JOINTS, 3):
        raise ValueError(f"targets: expected shape ({n_frames}, {sk.NUM_JOINTS}, 3), got {tg.shape}")
    if mk.shape != (n_frames, sk.NUM_JOINTS):
        raise ValueError(f"target_mask: expected shape ({n_frames}, {sk.NUM_JOINTS}), got {mk.shape}")
    if mk.dtype != bool:
        if not np.isin(mk, (0, 1)).all():
            raise ValueError("target_mask: expected booleans (or 0/1)")
        mk = mk.astype(bool)
    if not np.isfinite(tg[mk]).all():
        raise ValueError("targets: NaN/inf at a position the mask marks as constrained")
    return np.where(mk[..., None], tg, 0.0), mk


def _check_trajectory(trajectory) -> np.ndarray | None:
    if trajectory is None:
        return None
    arr = np.asarray(trajectory, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 2:
        raise ValueError(f"trajectory: expected shape (N >= 2, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("trajectory: contains NaN/inf")
    return arr


def _check_out(path, suffixes: tuple[str, ...]) -> Path:
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{p}: expected a file name ending in {' or '.join(suffixes)}")
    if not p.parent.exists():
        raise ValueError(f"{p}: folder {p.parent} does not exist")
    return p


# ------------------------------------------------------------------ panel reuse

class PanelCache:
    """Finished panels of side-by-side renders, (T, H, W, 3) uint8 each, keyed by everything
    that decides their pixels (joints, camera path, size, label). Successive edits of one
    source motion show the same source panel; drawing it once saves half of every later render."""

    def __init__(self, limit_bytes: int = PANEL_CACHE_BYTES):
        self.limit = int(limit_bytes)
        self._items: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0

    def get(self, key: str) -> np.ndarray | None:
        with self._lock:
            frames = self._items.get(key)
            if frames is not None:
                self._items.move_to_end(key)
                self.hits += 1
            return frames

    def put(self, key: str, frames: np.ndarray) -> None:
        if frames.nbytes > self.limit:
            return
        frames.setflags(write=False)      # shared by later renders: nobody may draw on it
        with self._lock:
            self._items[key] = frames
            self._items.move_to_end(key)
            while sum(f.nbytes for f in self._items.values()) > self.limit:
                self._items.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self.hits = 0

    def __len__(self) -> int:
        return len(self._items)


panel_cache = PanelCache()


# ------------------------------------------------------------------ one panel

@dataclass
class _Panel:
    """Everything needed to draw one motion in one viewport."""

    joints: np.ndarray
    camera: cam.CameraPath
    label: str | None = None
    tint: np.ndarray | None = None
    targets: geo.TargetGeometry | None = None
    trajectory: np.ndarray | None = None
    cmap: str = "attention"
    tint_label: str = "attention"
    skeleton: geo.SkeletonGeometry = field(init=False)

    def __post_init__(self):
        self.skeleton = geo.SkeletonGeometry(geo.body_scale(self.joints))
        right, up, back = (a[0] for a in self.camera.right_up_back())
        self.lights = style.light_dirs(right, up, back)
        self.view = back
        if self.tint is None:
            self.albedo = np.broadcast_to(style.PART_COLORS[sk.PART_OF_JOINT], (1, sk.NUM_JOINTS, 3))
        else:
            self.albedo = style.colormap(self.tint, self.cmap)

    @property
    def n_frames(self) -> int:
        return len(self.joints)

    def cache_key(self, size: tuple[int, int], samples: int) -> str | None:
        """What decides this panel's pixels, hashed; None for panels with extras (tints,
        targets, paths), which are drawn fresh."""
        if self.tint is not None or self.targets is not None or self.trajectory is not None:
            return None
        h = hashlib.sha256()
        for part in (np.ascontiguousarray(self.joints, np.float64), np.ascontiguousarray(self.camera.poses),
                     np.array([self.camera.yfov, *size, samples], np.float64)):
            h.update(part.tobytes())
        h.update(str(self.label).encode())
        return h.hexdigest()

    def block(self, frames: np.ndarray) -> dict[str, np.ndarray]:
        """Vertex rows for frame indices `frames` (already clamped to this motion)."""
        j = self.joints[frames]
        albedo = self.albedo if self.tint is None else self.albedo[frames]
        out = {"body": self.skeleton.body(j, albedo, self.lights, self.view),
               "shadow": self.skeleton.shadow(j, self.lights["shadow"][0])}
        if self.targets is not None and self.targets.capacity:
            out["markers"] = self.targets.dynamic(frames, j, self.lights, self.view)
        return out

    def install(self, eng) -> None:
        """Put this panel's meshes into the scene (sizes only; vertices come per frame)."""
        sg = self.skeleton
        eng.set_dynamic("body", sg.n_vertices, sg.faces)
        eng.set_dynamic("shadow", sg.n_shadow_vertices, sg.shadow_faces, blend=True)
        if self.targets is not None:
            eng.set_dynamic("markers", self.targets.n_dynamic_vertices, self.targets.dynamic_faces)
            eng.set_static("dots", self.targets.static(self.lights, self.view), self.targets.static_faces)
        else:
            eng.drop("markers")
            eng.drop("dots")
        if self.trajectory is not None:
            rows, faces = geo.path_ribbon(self.trajectory, 0.05 * self.skeleton.scale)
            rows[:, 6] = 1.0
            eng.set_static("path", rows, faces)
        else:
            eng.drop("path")

    def floor_shift(self, t: int) -> np.ndarray:
        # Move the floor with the camera in whole checker periods so the pattern stays put.
        period = 2 * style.FLOOR_TILE
        return np.round(self.camera.targets[t, [0, 2]] / period) * period


def draw_panels(eng, panels: list[_Panel], which: list[int], ts: Sequence[int], size: tuple[int, int]
                ) -> Iterator[tuple[int, dict[int, np.ndarray]]]:
    """Draw panels `which` at frames `ts` (ascending) -> (t, {panel: (H, W, 3) uint8}) per frame, with
    only the panels whose motion still runs at t (one that has ended holds its last frame: not drawn again).
    A render worker draws its share of a video with this too."""
    if len(which) == 1:
        panels[which[0]].install(eng)
    ts = np.asarray(ts, int)
    for start in range(0, len(ts), BLOCK):
        chunk = ts[start:start + BLOCK]
        blocks = {p: panels[p].block(np.minimum(chunk, panels[p].n_frames - 1)) for p in which}
        for i, t in enumerate(chunk):
            images = {}
            for p in which:
                panel = panels[p]
                if t >= panel.n_frames:
                    continue
                if len(which) > 1:
                    panel.install(eng)
                images[p] = eng.draw(size, panel.camera.yfov, panel.camera.poses[t], panel.floor_shift(t),
                                     {k: v[i] for k, v in blocks[p].items()})
            yield int(t), images


def _frames(scene: Scene, panels: list[_Panel], progress: Progress | None,
            antialias: bool = True) -> Iterator[np.ndarray]:
    """Yield finished frames (H, W * n_panels, 3) uint8 of `scene` (drawn as `panels`); shorter motions
    hold their last frame. antialias=False drops multisampling: about half the time per frame, with
    jagged edges. Idle render workers (salad.render.workers) draw the later frames meanwhile."""
    size, title = scene.size, scene.title
    w, h = size
    samples = style.MSAA_SAMPLES if antialias else 0
    total = max(p.n_frames for p in panels)
    statics = []
    for p in panels:
        patches = []
        if p.label:
            patches.append(overlay.label_patch(p.label, w, h, max_lines=1))
        if title and len(panels) == 1:
            patches.append(overlay.label_patch(title, w, h))
        if p.tint is not None:
            patches.append(overlay.legend_patch(w, h, p.cmap, p.tint_label))
        statics.append(patches)
    clock = overlay.Clock(w * len(panels), h, scene.fps, total)
    # Panels of a side-by-side render are kept and reused (see PanelCache); a single panel is
    # one frame per draw anyway and carries the render's own title.
    keys = [p.cache_key(size, samples) if len(panels) > 1 else None for p in panels]
    reused = [panel_cache.get(k) if k is not None else None for k in keys]
    fresh = [np.empty((p.n_frames, h, w, 3), np.uint8) if k is not None and r is None else None
             for p, k, r in zip(panels, keys, reused)]
    drawn = [i for i, r in enumerate(reused) if r is None]
    stats = {"frames": total, "panels": len(panels), "size": size, "draw_s": 0.0, "worker_frames": 0,
             "reused_panels": sum(r is not None for r in reused), "backend": gl_backend(), "msaa_samples": samples}
    started = time.perf_counter()
    last: list[np.ndarray | None] = [None] * len(panels)
    with engine() as eng:
        eng.renderer.samples = samples
        for lo, hi, job in worker_shares(scene, drawn, total, samples):
            here = None if job is not None else draw_panels(eng, panels, drawn, range(lo, hi), size)
            for t in range(lo, hi):
                t0 = time.perf_counter()
                images = job.frame(t) if job is not None else None
                if images is None:
                    if here is None:        # the worker failed: this process draws the rest of its share
                        here = draw_panels(eng, panels, drawn, range(t, hi), size)
                    images = next(here)[1]
                else:
                    stats["worker_frames"] += 1
                views = []
                for i, (p, patches, old, new) in enumerate(zip(panels, statics, reused, fresh)):
                    tp = min(t, p.n_frames - 1)
                    if old is not None:
                        views.append(old[tp])
                        continue
                    if i not in images:          # holding its last frame
                        views.append(last[i])
                        continue
                    if new is None:
                        img = images[i].copy()
                    else:
                        img = new[tp]
                        img[...] = images[i]
                    for patch in patches:
                        patch.blend(img)
                    last[i] = img
                    views.append(img)
                # a single panel is never held nor cached, so its view is this frame's own image
                frame = np.concatenate(views, axis=1) if len(views) > 1 else views[0]
                for j in range(1, len(views)):
                    frame[:, j * w] = (frame[:, j * w] * 0.55).astype(np.uint8)  # a thin seam between panels
                clock.patch(t).blend(frame)
                stats["draw_s"] += time.perf_counter() - t0
                yield frame
                if progress is not None:
                    progress(t + 1, total)
    for k, new in zip(keys, fresh):
        if new is not None:
            panel_cache.put(k, new)
    stats["total_s"] = time.perf_counter() - started
    _last_stats.clear()
    _last_stats.update(stats)


def _panels(motions: Sequence[np.ndarray], size, fps, labels=None, **extra) -> list[_Panel]:
    cams = cam.follow_camera(list(motions), fps, aspect=size[0] / size[1])
    labels = labels or [None] * len(motions)
    return [_Panel(m, c, label=l, **extra) for m, c, l in zip(motions, cams, labels)]


@dataclass
class Scene:
    """What a video shows, in plain values: a render worker rebuilds the same panels from them.
    labels=None: one motion alone (with title, tint, targets, trajectory); else one labelled panel each."""

    motions: list[np.ndarray]
    size: tuple[int, int]
    fps: float
    labels: list[str] | None = None
    title: str | None = None
    tint: np.ndarray | None = None
    targets: np.ndarray | None = None
    target_mask: np.ndarray | None = None
    trajectory: np.ndarray | None = None
    cmap: str = "attention"
    tint_label: str = "attention"

    def panels(self) -> list[_Panel]:
        """The panels to draw; checks the scene's arrays on the way (ValueError)."""
        if self.labels is not None:
            return _panels(self.motions, self.size, self.fps, labels=self.labels)
        j = _check_joints(self.motions[0])
        tint = _check_tint(self.tint, len(j))
        tg = _check_targets(self.targets, self.target_mask, len(j))
        traj = _check_trajectory(self.trajectory)
        if tint is not None:
            style.colormap(np.zeros(1), self.cmap)  # an unknown colour map fails here, before any work
        panels = _panels([j], self.size, self.fps, tint=tint, trajectory=traj, cmap=self.cmap,
                         tint_label=str(self.tint_label))
        if tg is not None:
            panels[0].targets = geo.TargetGeometry(tg[0], tg[1], panels[0].skeleton.scale)
        return panels


# ------------------------------------------------------------------ public API

def render_frames(joints: np.ndarray, fps: float = 20, size: tuple[int, int] = DEFAULT_SIZE,
                  title: str | None = None, tint: np.ndarray | None = None,
                  targets: np.ndarray | None = None, target_mask: np.ndarray | None = None,
                  trajectory: np.ndarray | None = None, cmap: str = "attention",
                  tint_label: str = "attention", progress: Progress | None = None,
                  antialias: bool = True) -> np.ndarray:
    """Render a motion (T, 22, 3) to frames (T, H, W, 3) uint8; see render_video for options."""
    scene = Scene([joints], _check_size(size), _check_fps(fps), title=title, tint=tint, targets=targets,
                  target_mask=target_mask, trajectory=trajectory, cmap=cmap, tint_label=tint_label)
    with closing(_frames(scene, scene.panels(), progress, antialias)) as frames:
        return np.stack(list(frames))


def render_video(joints: np.ndarray, path: str | os.PathLike, fps: float = 20,
                 size: tuple[int, int] = DEFAULT_SIZE, title: str | None = None,
                 tint: np.ndarray | None = None, targets: np.ndarray | None = None,
                 target_mask: np.ndarray | None = None, trajectory: np.ndarray | None = None,
                 cmap: str = "attention", tint_label: str = "attention",
                 progress: Progress | None = None, antialias: bool = True) -> Path:
    """Render a motion (T, 22, 3), metres, Y up, to an H.264 MP4 that browsers play.

    title: burned in top-left. tint: (T, 22) values in [0, 1] that recolour joints through
    `cmap` (e.g. one word's attention), with a colour bar captioned `tint_label`.
    targets (T, 22, 3) + target_mask (T, 22) bool: drawn as dots for every constrained
    frame, and as larger markers tied to their joints on the current frame.
    trajectory: (N, 3) path drawn on the floor. progress(done, total) is called after
    every frame. antialias=False (no multisampling) renders in about half the time, for
    previews. The file appears only once it is complete.
    """
    out = _check_out(path, (".mp4",))
    scene = Scene([joints], _check_size(size), _check_fps(fps), title=title, tint=tint, targets=targets,
                  target_mask=target_mask, trajectory=trajectory, cmap=cmap, tint_label=tint_label)
    with closing(_frames(scene, scene.panels(), progress, antialias)) as frames:
        _encode(frames, out, scene.fps)
    return out


def render_side_by_side(motions: Sequence[np.ndarray], labels: Sequence[str], path: str | os.PathLike,
                        fps: float = 20, size: tuple[int, int] = PANEL_SIZE,
                        progress: Progress | None = None, antialias: bool = True) -> Path:
    """Render motions next to each other in one synchronised MP4, one labelled panel of
    `size` each; all panels share the viewing direction and zoom, each follows its own
    character, and shorter motions hold their last frame. antialias as render_video."""
    out = _check_out(path, (".mp4",))
    size, fps = _check_size(size), _check_fps(fps)
    if isinstance(motions, np.ndarray) and motions.ndim == 3:
        raise ValueError("motions: expected a list of (T, 22, 3) arrays, got a single motion")
    if len(motions) < 1 or len(motions) > 6:
        raise ValueError(f"motions: expected 1 to 6 motions, got {len(motions)}")
    labels = list(labels)
    if len(labels) != len(motions):
        raise ValueError(f"labels: expected one label per motion ({len(motions)}), got {len(labels)}")
    scene = Scene([_check_joints(m, f"motions[{i}]") for i, m in enumerate(motions)], size, fps,
                  labels=[str(l) for l in labels])
    with closing(_frames(scene, scene.panels(), progress, antialias)) as frames:
        _encode(frames, out, fps)
    return out


def _encode(frames: Iterator[np.ndarray], out: Path, fps: float) -> None:
    import imageio.v2 as imageio

    with atomic_path(out) as tmp:
        writer = imageio.get_writer(
            tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
            quality=None, macro_block_size=2, ffmpeg_log_level="error",
            output_params=["-preset", X264_PRESET, "-crf", str(X264_CRF), "-movflags", "+faststart"])
        try:
            for frame in frames:
                writer.append_data(frame)
        finally:
            writer.close()


def _frames_or_render(data, fps, size, title, **kw) -> np.ndarray:
    arr = np.asarray(data)
    if arr.ndim == 4 and arr.shape[-1] == 3 and arr.dtype == np.uint8:
        if len(arr) == 0:
            raise ValueError("frames: empty")
        return arr
    return render_frames(arr, fps=fps, size=size, title=title, **kw)


def save_gif(joints_or_frames: np.ndarray, path: str | os.PathLike, fps: float = 20,
             size: tuple[int, int] = (320, 320), title: str | None = None, stride: int = 2,
             **render_kw) -> Path:
    """A looping GIF of a motion (T, 22, 3) or of rendered frames (T, H, W, 3) uint8, keeping
    every `stride`-th frame (GIFs get big fast)."""
    from PIL import Image

    out = _check_out(path, (".gif",))
    fps = _check_fps(fps)
    if int(stride) < 1:
        raise ValueError(f"stride: must be >= 1, got {stride}")
    frames = _frames_or_render(joints_or_frames, fps, size, title, **render_kw)[::int(stride)]
    images = [Image.fromarray(f) for f in frames]
    # One palette for all frames (per-frame palettes make the floor flicker), learnt from a
    # few frames so colours that come and go (tints, markers) are in it.
    sample = frames[np.linspace(0, len(frames) - 1, min(6, len(frames))).round().astype(int)]
    palette = Image.fromarray(np.concatenate(list(sample), axis=0)).quantize(
        colors=255, method=Image.Quantize.MEDIANCUT)
    q = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    with atomic_path(out) as tmp:
        q[0].save(tmp, format="GIF", save_all=True, append_images=q[1:], loop=0,
                  duration=int(round(1000 * stride / fps)), optimize=False, disposal=1)
    return out


def save_frame_strip(joints_or_frames: np.ndarray, path: str | os.PathLike, n: int = 6,
                     fps: float = 20, size: tuple[int, int] = (256, 256),
                     title: str | None = None, **render_kw) -> Path:
    """A PNG of `n` evenly spaced frames side by side (for READMEs and papers)."""
    from PIL import Image

    out = _check_out(path, (".png",))
    if int(n) < 1:
        raise ValueError(f"n: must be >= 1, got {n}")
    frames = _frames_or_render(joints_or_frames, fps, size, None, **render_kw)
    idx = np.unique(np.linspace(0, len(frames) - 1, int(n)).round().astype(int))
    tiles = [frames[i].copy() for i in idx]
    if title:  # once, on the first tile, rather than repeated on every one
        overlay.label_patch(title, tiles[0].shape[1], tiles[0].shape[0]).blend(tiles[0])
    gap = np.full((tiles[0].shape[0], 2, 3), 255, np.uint8)
    strip = np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)
    with atomic_path(out) as tmp:
        Image.fromarray(strip).save(tmp, format="PNG", optimize=False)
    return out


def warm_up(size: tuple[int, int] = DEFAULT_SIZE) -> str:
    """Start the GL backend and compile the shaders now (about 2 s once per process) so the
    first real render is fast; returns the backend name."""
    rest = np.zeros((2, sk.NUM_JOINTS, 3))
    rest[:, :, 1] = np.linspace(0.05, 1.7, sk.NUM_JOINTS)
    rest[:, :, 0] = np.where(np.arange(sk.NUM_JOINTS) % 2, 0.1, -0.1)
    render_frames(rest, size=size)
    return gl_backend()


def last_render_stats() -> dict:
    """Timings of the most recent render: frames, panels, size, draw_s, total_s, and worker_frames (drawn by
    render workers)."""
    return dict(_last_stats)
