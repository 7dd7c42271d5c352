"""What the studio does, without any UI: generate a motion with its attention, save and
render it, and build (cached) attention views. Every model call goes through the public
pipeline API and every picture through salad.render."""
from __future__ import annotations

import os
import re
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np

from salad.motion import skeleton as sk

from .figures import frames_to_restyle_slider
from .session import Result, Session
from .validation import AttentionRequest, GenerateRequest
from .workspace import Workspace

Progress = Callable[[str, int, int], None]   # (stage, done, total)


def _quiet(stage: str, done: int, total: int) -> None:
    pass


def file_stem(req: GenerateRequest) -> str:
    """A readable, safe file name stem: the prompt's first words and the seed."""
    slug = re.sub(r"[^a-z0-9]+", "-", req.prompt.lower()).strip("-")[:40].strip("-") or "motion"
    return f"{slug}_seed{req.seed}"


def _save_npz(path: Path, **arrays) -> Path:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def word_tint(att_word: np.ndarray) -> np.ndarray:
    """A word's (7 parts, T) attention -> (T, 22 joints) in [0, 1], scaled by its maximum so
    the pattern over the body shows whatever the word's overall strength."""
    per_joint = np.asarray(att_word, dtype=np.float64)[sk.PART_OF_JOINT].T
    top = per_joint.max()
    return np.clip(per_joint / top, 0.0, 1.0) if top > 0 else np.zeros_like(per_joint)


class Studio:
    """Generation and attention views over one loaded pipeline, for many sessions."""

    def __init__(self, pipe, workspace: Workspace):
        self.pipe = pipe
        self.workspace = workspace
        # Sampling swaps an attention controller into the shared denoiser, so only one
        # sampling runs at a time; rendering (its own lock) overlaps with the next sampling.
        self._model_lock = threading.Lock()

    # ------------------------------------------------------------ sessions
    def session(self, current: Session | None, session_hash: str) -> Session:
        folder = self.workspace.session_dir(session_hash)
        if isinstance(current, Session):
            current.folder = folder
            return current
        return Session(self.workspace.session_key(session_hash), folder)

    # ------------------------------------------------------------ generation
    def generate(self, session: Session, req: GenerateRequest, progress: Progress = _quiet) -> Result:
        """Sample, save (NPY, NPZ, BVH) and render (MP4) one motion; it becomes the session's current one."""
        from salad.render import render_video

        folder = session.new_folder()
        t0 = time.perf_counter()
        if self._model_lock.locked():
            progress("waiting for the model", 0, req.steps)
        with self._model_lock:
            t_wait = time.perf_counter()
            motion = self.pipe.generate(req.prompt, seconds=req.seconds, seed=req.seed, steps=req.steps,
                                        cfg=req.cfg, sampler=req.sampler, return_attention=True,
                                        progress=lambda i, n: progress("sampling", i, n))
        t1 = time.perf_counter()
        stem = file_stem(req)
        files = {ext: motion.save(folder / f"{stem}.{ext}") for ext in ("npy", "npz", "bvh")}
        files["mp4"] = render_video(motion.joints, folder / f"{stem}.mp4", fps=motion.fps, title=motion.text,
                                    progress=lambda i, n: progress("rendering", i, n))
        t2 = time.perf_counter()
        result = Result(req, motion, folder, files,
                        {"wait_s": t_wait - t0, "sample_s": t1 - t_wait, "render_s": t2 - t1, "total_s": t2 - t0})
        session.add(result)
        return result

    def skeleton_figure(self, result: Result):
        from salad.render import skeleton_figure

        return result.cached(("skeleton",), lambda: frames_to_restyle_slider(
            skeleton_figure(result.motion.joints, fps=result.motion.fps)))

    # ------------------------------------------------------------ attention
    def aggregate(self, result: Result, req: AttentionRequest) -> np.ndarray:
        """(words, 7, T) attention averaged over the chosen layers and steps."""
        return result.cached(("aggregate", req.layers, req.steps), lambda: result.motion.attention.aggregate(
            layers=list(req.layers), steps=req.steps))

    def word_heatmap(self, result: Result, req: AttentionRequest):
        from salad.render import attention_heatmap

        words = result.motion.attention.words
        return result.cached(("heatmap", req.word, req.layers, req.steps), lambda: attention_heatmap(
            self.aggregate(result, req)[req.word], words[req.word], fps=result.motion.fps))

    def overview(self, result: Result, req: AttentionRequest):
        from salad.render import attention_overview

        return result.cached(("overview", req.layers, req.steps), lambda: attention_overview(
            self.aggregate(result, req), result.motion.attention.words, fps=result.motion.fps))

    def attention_files(self, result: Result, req: AttentionRequest) -> list[Path]:
        """NPZ (the chosen aggregation plus the raw per-step, per-layer maps) and PNG (heatmaps)."""
        from salad.render import attention_png

        def make() -> list[Path]:
            maps = result.motion.attention
            agg = self.aggregate(result, req)
            stem = f"{file_stem(result.request)}_attention_L{'-'.join(map(str, req.layers))}" \
                   f"_s{req.steps[0] + 1}-{req.steps[1]}"
            npz = _save_npz(result.folder / f"{stem}.npz", words=np.array(maps.words), attention=agg.astype(np.float32),
                            parts=np.array(sk.BODY_PARTS.names), layers=np.array(req.layers),
                            steps=np.array(req.steps), fps=np.array(result.motion.fps),
                            raw=maps.data.astype(np.float32), raw_layers=np.array(maps.layers),
                            frames=np.array(maps.frames))
            png = attention_png(agg, maps.words, result.folder / f"{stem}.png", fps=result.motion.fps)
            return [npz, Path(png)]

        return result.cached(("files", req.layers, req.steps), make)

    def word_video(self, result: Result, req: AttentionRequest, progress: Progress = _quiet) -> Path:
        """The skeleton video with joints tinted by one word's attention."""
        from salad.render import render_video

        def make() -> Path:
            word = result.motion.attention.words[req.word]
            tint = word_tint(self.aggregate(result, req)[req.word])
            name = f"{file_stem(result.request)}_word{req.word}-{re.sub(r'[^a-z0-9]+', '', word)[:16]}" \
                   f"_L{'-'.join(map(str, req.layers))}_s{req.steps[0] + 1}-{req.steps[1]}.mp4"
            return render_video(result.motion.joints, result.folder / name, fps=result.motion.fps,
                                title=result.motion.text, tint=tint, tint_label=f"“{word}”",
                                progress=lambda i, n: progress("rendering", i, n))

        return result.cached(("video", req.word, req.layers, req.steps), make)
