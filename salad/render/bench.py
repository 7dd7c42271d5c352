"""Measure rendering speed: `python -m salad.render.bench [--frames 120] [--sizes 384 448] [--workers 1]`.

Renders a clip (the HumanML3D sample, or --motion FILE.npy) to MP4 at each size, then the
studio's edit view (two panels side by side, drawn fresh and with the source panel reused)
and the attention PNG, and prints wall time, frames per second and where the time went;
with --workers N, N render workers (salad.render.workers) draw a share of each video.
Set PYOPENGL_PLATFORM=egl or osmesa to measure one backend; each backend needs its own process.
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


def _timed(render, frames: int, **row) -> dict:
    """Wall and CPU time of one render (ours and the encoder's), with the renderer's own stats."""
    from .video import last_render_stats

    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu0, t0 = time.process_time(), time.perf_counter()
    render()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    st = last_render_stats()
    return dict(row, frames=frames, wall_s=wall, fps=frames / wall, render_cpu_s=cpu,
                encoder_cpu_s=(c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime),
                draw_s=st.get("draw_s", 0.0), worker_frames=st.get("worker_frames", 0),
                reused_panels=st.get("reused_panels", 0))


def _best(rows: list[dict]) -> dict:
    return min(rows, key=lambda r: r["wall_s"])


def run(motion: np.ndarray, frames: int = 120, sizes=(384, 448), repeats: int = 3) -> list[dict]:
    """Rows of timings: kind "single" per size, "side-by-side" (fresh and "reused source")
    at the studio's panel size, and "png" (attention heatmaps of a 10-word prompt)."""
    import salad.render.backend as backend
    from .figures import attention_png
    from .video import PANEL_SIZE, panel_cache, render_side_by_side, render_video

    walk = np.resize(motion, (frames,) + motion.shape[1:]) if len(motion) < frames else motion[:frames]
    edited = walk * np.array([-1.0, 1.0, 1.0], dtype=walk.dtype)   # another motion of the same length
    gl = backend.gl_backend()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.mp4"
        t0 = time.perf_counter()
        render_video(walk[:2], out, size=(64, 64))
        first = time.perf_counter() - t0
        for s in sizes:
            rows.append(_best([_timed(lambda: render_video(walk, out, size=(s, s), title="a person walks forward"),
                                      frames, kind="single", backend=gl, size=s, startup_s=first)
                               for _ in range(repeats)]))

        def pair(reuse: bool):
            panel_cache.clear()
            if reuse:     # an earlier edit of the same source left its panel behind
                render_side_by_side([walk, walk[:8]], ["source", "edited"], out)
            return _timed(lambda: render_side_by_side([walk, edited], ["source", "edited"], out), frames,
                          kind="side-by-side", backend=gl, size=PANEL_SIZE[0], startup_s=first,
                          note="reused source" if reuse else "fresh")

        rows.append(_best([pair(False) for _ in range(repeats)]))
        rows.append(_best([pair(True) for _ in range(repeats)]))
        panel_cache.clear()
        att = np.random.default_rng(0).random((10, 7, frames))
        words = [f"word{i}" for i in range(10)]
        png = Path(tmp) / "attention.png"
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            attention_png(att, words, png)
            times.append(time.perf_counter() - t0)
        rows.append(dict(kind="png", backend=gl, words=10, frames=frames, wall_s=min(times),
                         bytes=png.stat().st_size))
    return rows


def describe(r: dict) -> str:
    """One printed line per row of `run`."""
    if r["kind"] == "png":
        return f"attention PNG, {r['words']} words x {r['frames']} frames: {r['wall_s']:.2f} s ({r['bytes'] // 1000} kB)"
    what = "single      " if r["kind"] == "single" else f"side-by-side ({r['note']})"
    panels = "" if r["kind"] == "single" else f" x2 panels, {r['reused_panels']} reused"
    return (f"{r['backend']:6s} {what} {r['size']:4d}px{panels} {r['frames']} frames: {r['wall_s']:.2f} s "
            f"({r['fps']:.0f} fps)  draw {r['draw_s']:.2f} s, {r.get('worker_frames', 0)} frames by workers, "
            f"CPU render {r['render_cpu_s']:.2f} s + encoder {r['encoder_cpu_s']:.2f} s; "
            f"first call incl. GL start-up {r['startup_s']:.2f} s")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--sizes", type=int, nargs="+", default=[384, 448])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--motion", type=Path, default=None, help="(T, 22, 3) .npy; default: HumanML3D sample")
    ap.add_argument("--workers", type=int, default=0, help="render workers drawing beside this process (default 0)")
    args = ap.parse_args(argv)
    motion = np.load(args.motion or _default_motion(), allow_pickle=False)
    if args.workers:
        from .workers import start, wait_ready

        start(args.workers)
        wait_ready(args.workers)
    for r in run(motion, args.frames, args.sizes, args.repeats):
        print(describe(r))


if __name__ == "__main__":
    main()
