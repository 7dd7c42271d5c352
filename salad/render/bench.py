"""Measure rendering speed: `python -m salad.render.bench [--frames 120] [--sizes 384 448]`.

Renders a 6 s clip (the HumanML3D sample, or --motion FILE.npy) to MP4 at each size and
prints wall time, frames per second and where the time went. Set PYOPENGL_PLATFORM=egl
or osmesa to measure one backend; each backend needs its own process.
"""
from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np


def _default_motion() -> Path:
    """The HumanML3D sample clip from the shared data folder."""
    env = os.environ.get("SALAD_SHARED_DATA")
    root = Path(__file__).resolve().parents[2]
    for d in ([Path(env)] if env else []) + [root.parent / "shared" / "data"]:
        clip = d / "humanml3d-sample" / "new_joints" / "012314.npy"
        if clip.is_file():
            return clip
    raise SystemExit("no motion to render: pass --motion FILE.npy with a (T, 22, 3) array "
                     "or set SALAD_SHARED_DATA")


def run(motion: np.ndarray, frames: int = 120, sizes=(384, 448), repeats: int = 3) -> list[dict]:
    from . import backend
    from .video import last_render_stats, render_video

    walk = np.resize(motion, (frames,) + motion.shape[1:]) if len(motion) < frames else motion[:frames]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.mp4"
        t0 = time.perf_counter()
        render_video(walk[:2], out, size=(64, 64))
        first = time.perf_counter() - t0
        for s in sizes:
            best = None
            for _ in range(repeats):
                c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu0, t0 = time.process_time(), time.perf_counter()
                render_video(walk, out, size=(s, s))
                wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
                c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                enc = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
                st = last_render_stats()
                row = dict(backend=backend.gl_backend(), size=s, frames=frames, wall_s=wall,
                           fps=frames / wall, render_cpu_s=cpu, encoder_cpu_s=enc,
                           draw_s=st["draw_s"], geometry_s=st["geometry_s"], startup_s=first)
                if best is None or wall < best["wall_s"]:
                    best = row
            rows.append(best)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--sizes", type=int, nargs="+", default=[384, 448])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--motion", type=Path, default=None, help="(T, 22, 3) .npy; default: HumanML3D sample")
    args = ap.parse_args(argv)
    motion = np.load(args.motion or _default_motion(), allow_pickle=False)
    for r in run(motion, args.frames, args.sizes, args.repeats):
        print(f"{r['backend']:6s} {r['size']:4d}px {r['frames']} frames: {r['wall_s']:.2f} s "
              f"({r['fps']:.0f} fps)  draw {r['draw_s']:.2f} s, geometry {r['geometry_s']:.2f} s, "
              f"CPU render {r['render_cpu_s']:.2f} s + encoder {r['encoder_cpu_s']:.2f} s; "
              f"first call incl. GL start-up {r['startup_s']:.2f} s")


if __name__ == "__main__":
    main()
