"""What the studio does, without any UI: generate a motion with its attention, edit one by
attention modulation, guide one with control targets; save and render the results, and build
(cached) views of them. Every model call goes through the public pipeline API and every
picture through salad.render.

A result's video comes in two renders: a preview without antialiasing at about half the pixels
(a third of the time), made with the result and shown at once, and the antialiased MP4 at full
size, the one among the downloads, made on request (`full_video`) and kept on the result.
Generated, edited and guided motions are previewed before their planted-feet refinement (a
decoder forward and backward per L-BFGS evaluation: about as long again as the rest of the request
on the student); `refine_feet` runs it before the full video, and only then are their motion files
written."""
from __future__ import annotations

import logging
import re
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np

from salad.motion import skeleton as sk

from . import controls
from .figures import control_top_view, frames_to_restyle_slider, note_figure, plot_data
from .model_thread import ModelThread
from .session import Result, Session
from .validation import AttentionRequest, ControlRequest, EditRequest, GenerateRequest
from .workspace import Workspace
from salad.files import atomic_write

log = logging.getLogger("salad.studio")
StageProgress = Callable[[str, int, int], None]   # (stage, done, total)
# Words an edit may add or swap that carry no motion of their own ("a" -> "an" before an adjective).
FUNCTION_WORDS = frozenset("a an the their his her its and or with to of in on at while as".split())
# Motion files (NPY, NPZ, BVH) are written here while the video renders: the video is what
# the user waits for, and the writes are mostly I/O and NumPy outside the GIL.
file_writer = ThreadPoolExecutor(max_workers=2, thread_name_prefix="salad-save")
# The downloads of each kind of result, in the order the page lists them ("mp4": the antialiased
# video, listed once it is rendered; the preview never is).
DOWNLOADS = {"generate": ("mp4", "bvh", "npy", "features", "npz"),
             "control": ("mp4", "bvh", "npy", "features", "npz", "signal"),
             "real": ("mp4", "bvh", "npy", "features")}
# The software rasteriser's time goes with the pixels: the preview is drawn at ~0.7x the full
# video's width and height (salad.render's 448 px single view and 384 px panels).
PREVIEW_SIZE, PREVIEW_PANEL_SIZE = (320, 320), (272, 272)
# Previews also draw every other frame at half the frame rate: on a software rasteriser each frame
# costs 5-9 ms, which made rendering 60-80% of a request, and the full video replaces them anyway.
PREVIEW_STRIDE = 2
EDIT_DOWNLOADS = ("edited_bvh", "source_bvh", "edited_npy", "source_npy", "edited_features", "source_features",
                  "edited_npz", "source_npz")


def quiet(stage: str, done: int, total: int) -> None:
    """A StageProgress that reports nowhere."""


def slug(text: str, limit: int = 40) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:limit].strip("-")


def file_stem(req) -> str:
    """A readable, safe file name stem: the (edited) prompt's first words, what was done and the seed."""
    if isinstance(req, EditRequest):
        return f"{slug(req.edited_prompt, 32) or 'motion'}_{req.mode}_seed{req.seed}"
    if isinstance(req, ControlRequest):
        return f"{slug(req.prompt, 32) or 'motion'}_{req.task}_seed{req.seed}"
    return f"{slug(req.prompt) or 'motion'}_seed{req.seed}"


def _save_npz(path: Path, **arrays) -> Path:
    return atomic_write(path, lambda f: np.savez(f, **arrays))


def save_motion(motion, folder: Path, stem: str, prefix: str = "") -> dict[str, Path]:
    """NPY joints, NPY features, NPZ (both) and BVH of a motion; keys carry `prefix`. The two NPY
    files end in _joints / _features: a download list that shortens long names keeps their ends."""
    files = {f"{prefix}{ext}": motion.save(folder / f"{stem}{'_joints' if ext == 'npy' else ''}.{ext}")
             for ext in ("npy", "npz", "bvh")}
    files[f"{prefix}features"] = atomic_write(folder / f"{stem}_features.npy",
                                             lambda f: np.save(f, motion.features.astype(np.float32)))
    return files


def video_path(result: Result, preview: bool = False) -> Path:
    """Where a result's video goes: <stem>.mp4 (an edit's <stem>_side-by-side.mp4), or its
    preview <stem>[_side-by-side]_preview.mp4."""
    stem = file_stem(result.request) + ("_side-by-side" if result.kind == "edit" else "")
    return result.folder / f"{stem}{'_preview' if preview else ''}.mp4"


def attention_arrays(maps, prefix: str = "") -> dict[str, np.ndarray]:
    """An AttentionMaps as NPZ entries: the all-layers, all-steps mean and the raw maps."""
    return {f"{prefix}words": np.array(maps.words), f"{prefix}attention": maps.aggregate().astype(np.float32),
            f"{prefix}raw": maps.data.astype(np.float32), f"{prefix}raw_layers": np.array(maps.layers),
            f"{prefix}frames": np.array(maps.frames)}


def word_tint(att_word: np.ndarray) -> np.ndarray:
    """A word's (7 parts, T) attention -> (T, 22 joints) in [0, 1], scaled by its maximum so
    the pattern over the body shows whatever the word's overall strength."""
    per_joint = np.asarray(att_word, dtype=np.float64)[sk.PART_OF_JOINT].T
    top = per_joint.max()
    return np.clip(per_joint / top, 0.0, 1.0) if top > 0 else np.zeros_like(per_joint)


def refinement_pending(result: Result) -> bool:
    """Whether a result's motions still wait for their planted-feet refinement (they keep their
    pending refinement until Studio.refine_feet)."""
    return any(m is not None and m.pending_refinement is not None for m in (result.motion, result.source))


def motion_files(result: Result) -> list[tuple]:
    """(motion, file stem, download key prefix) of each motion file set a result saves: an edit's
    source and edited motions, else its one motion."""
    stem = file_stem(result.request)
    if result.kind == "edit":
        return [(result.source, f"{stem}_source", "source_"), (result.motion, f"{stem}_edited", "edited_")]
    return [(result.motion, stem, "")]


def save_later(result: Result) -> list:
    """The writes of a result's motion files on the file writer (futures), or none while its
    refinement is pending: Studio.refine_feet writes them then."""
    if refinement_pending(result):
        return []
    return [file_writer.submit(save_motion, m, result.folder, stem, prefix) for m, stem, prefix in motion_files(result)]


def offered_samplers(pipe) -> tuple[str, ...]:
    """The samplers the studio offers over `pipe`: the teacher's, and the distilled student's
    ("consistency") when the model has one."""
    return ("dpm-sde", "ddim", "dpm") + (("consistency",) if getattr(pipe, "student", None) is not None else ())


class Studio:
    """Generation and attention views over one loaded pipeline, for many sessions."""

    def __init__(self, pipe, workspace: Workspace, control_examples: Path | None = None, sampler: str = "auto",
                 model_thread: ModelThread | None = None):
        self.pipe = pipe
        # every model call runs on this thread (app.model_thread says why) until close(); at full speed only
        # if it is the thread that loaded `pipe` (a thread made here samples about half as fast)
        self.model_thread = model_thread or ModelThread()
        self.workspace = workspace
        self.control_examples = control_examples      # a folder of control .npy files, or None
        self.samplers = offered_samplers(pipe)
        edit = control = sampler
        if sampler == "auto":
            # the student starts only the panels its checkpoint says it was measured fit for (the embedded
            # one: motions from text and guided control, not edits; assets/RESULTS.md, *Session 68*); otherwise text
            # and edits take the teacher in dpm-sde's 25 steps (DDIM-50's fidelity table in half the time) and
            # guided control DDIM, the one teacher sampler it guides. Edits are their own use: a student can
            # make motions as well as its teacher and still follow an edited prompt worse.
            sampler = "consistency" if pipe.student_preferred("text") else "dpm-sde"
            edit = "consistency" if pipe.student_preferred("edit") else "dpm-sde"
            control = "consistency" if pipe.student_preferred("control") else "ddim"
        elif sampler == "consistency" and sampler not in self.samplers:
            log.warning("the consistency sampler was asked for but %s has no consistency student (a consistency/ "
                        "checkpoint); the panels default to the teacher", pipe.source or "the model")
            sampler, edit, control = "dpm-sde", "dpm-sde", "ddim"
        elif sampler not in self.samplers:
            raise ValueError(f"sampler must be one of {', '.join(self.samplers)}, got {sampler!r}")
        self.default_sampler = sampler                # what the Generate panel starts with
        self.edit_sampler = edit                      # the Edit and Real motion panels
        self.control_sampler = control                # the Control panel
        # Sampling swaps an attention controller into the shared denoiser, so only one
        # sampling runs at a time; rendering (its own lock) overlaps with the next sampling.
        self._model_lock = threading.Lock()

    def close(self) -> None:
        """Stop the model thread; the studio takes no more model calls."""
        self.model_thread.close()

    # ------------------------------------------------------------ sessions
    def session(self, current: Session | None, session_hash: str) -> Session:
        folder = self.workspace.session_dir(session_hash)
        if isinstance(current, Session):
            current.folder = folder
            return current
        return Session(self.workspace.session_key(session_hash), folder)

    # ------------------------------------------------------------ generation
    def sample_locked(self, steps: int, progress: StageProgress, run: Callable):
        """run(report) under the model lock, on the model thread -> (its value, {"wait_s", "sample_s"})."""
        t0 = time.perf_counter()
        if self._model_lock.locked():
            progress("waiting for the model", 0, steps)
        with self._model_lock:
            t1 = time.perf_counter()
            value = self.model_thread.run(run, lambda i, n: progress("sampling", i, n))
        return value, {"wait_s": t1 - t0, "sample_s": time.perf_counter() - t1}

    @staticmethod
    def rendered(progress: StageProgress, render: Callable) -> tuple[Path, float]:
        """render(report) reporting as "rendering" -> (its path, seconds)."""
        t0 = time.perf_counter()
        path = render(lambda i, n: progress("rendering", i, n))
        return path, time.perf_counter() - t0

    def _render(self, result: Result, path: Path, antialias: bool, progress: StageProgress) -> Path:
        """Draw a result's video: a generated motion alone, an edit's source and edited motions
        side by side, a guided motion with its targets (and a path on the floor)."""
        from salad.render import render_side_by_side, render_video

        m = result.motion
        report = lambda i, n: progress("rendering", i, n)   # noqa: E731
        size = {} if antialias else {"size": PREVIEW_PANEL_SIZE if result.kind == "edit" else PREVIEW_SIZE}
        step = 1 if antialias else PREVIEW_STRIDE
        fps = m.fps / step
        if result.kind == "edit":
            return render_side_by_side([result.source.joints[::step], m.joints[::step]], ["source", "edited"], path,
                                       fps=fps, progress=report, antialias=antialias, **size)
        if result.kind == "control":
            # Free coordinates of a target take the motion's own value, so a pelvis path's markers
            # ride at pelvis height while its ribbon lies on the floor.
            sig, n = result.signal, m.frames
            shown = np.where(sig.mask[:n], sig.targets[:n], m.joints)
            return render_video(m.joints[::step], path, fps=fps, title=m.text, targets=shown[::step],
                                target_mask=sig.joint_mask()[:n][::step], trajectory=controls.pelvis_path(sig, n),
                                progress=report, antialias=antialias, **size)
        if result.kind == "generate":
            return render_video(m.joints[::step], path, fps=fps, title=m.text, progress=report, antialias=antialias,
                                **size)
        raise ValueError(f"no video is rendered here for a {result.kind} result")

    def _finish(self, session: Session, result: Result, saved: list, progress: StageProgress) -> Result:
        """Render `result`'s preview while its motion files (`saved`, futures of file dicts) are
        written, then make it the session's latest of its kind. A failure removes the result's folder."""
        # Building the plotly figure on another thread meanwhile was measured and gained nothing
        # (1.16 s vs 1.18 s per generation): the render already keeps both cores busy.
        started = time.perf_counter()
        try:
            preview = self._render(result, video_path(result, preview=True), False, progress)
            result.timings["render_s"] = time.perf_counter() - started
            files = {"preview": preview}
            for future in saved:
                files |= future.result()
        except BaseException:
            for future in saved:
                future.cancel() or future.exception()   # let the writers finish before the folder goes
            shutil.rmtree(result.folder, ignore_errors=True)
            raise
        result.files = files
        session.add(result)
        return result

    def generate(self, session: Session, req: GenerateRequest, progress: StageProgress = quiet) -> Result:
        """Sample, save (NPY joints and features, NPZ, BVH) and preview (MP4 without antialiasing)
        one motion; it becomes the session's current one. An identical earlier request of the
        session is answered from its files."""
        reused = session.reuse("generate", req)
        if reused is not None:
            return reused
        folder = session.new_folder()
        motion, timings = self.sample_locked(req.steps, progress, lambda report: self.pipe.generate(
            req.prompt, seconds=req.seconds, seed=req.seed, steps=req.steps, cfg=req.cfg, sampler=req.sampler,
            return_attention=True, progress=report, foot_lock=req.foot_lock, foot_refine=False))
        result = Result(req, motion, folder, {}, timings)
        return self._finish(session, result, save_later(result), progress)

    def refine_feet(self, result: Result, progress: StageProgress = quiet) -> None:
        """Refine the planted feet of a result's motions where that was deferred
        (refinement_pending), then write their motion files; the skeleton and top views are built
        again from the refined motion. Runs once per result, whoever asks first."""
        def make() -> bool:
            with self._model_lock:
                if not refinement_pending(result):        # another request finished it meanwhile
                    return True
                progress("refining the planted feet", 0, 1)
                t0 = time.perf_counter()
                motion, source = self.model_thread.run(self.pipe.refine_feet, result.motion), result.source
                if source is not None:
                    source = self.model_thread.run(self.pipe.refine_feet, source)
                result.timings["refine_s"] = time.perf_counter() - t0
                result.motion, result.source = motion, source
            result.forget(("skeleton",))
            result.forget(("top view",))
            files = {}
            for m, stem, prefix in motion_files(result):
                files |= save_motion(m, result.folder, stem, prefix)
            result.files = result.files | files
            progress("refining the planted feet", 1, 1)
            return True

        if refinement_pending(result):
            result.cached(("feet refined",), make)

    # ------------------------------------------------------------ videos
    def full_video(self, result: Result, progress: StageProgress = quiet) -> Path:
        """The result's antialiased MP4 (the downloadable one), rendered on first use and kept:
        it joins the result's files (and so its downloads) as "mp4"."""
        if result.kind == "real":          # rendered with the result
            return result.files["mp4"]

        def make() -> Path:
            self.refine_feet(result, progress)
            t0 = time.perf_counter()
            path = self._render(result, video_path(result), True, progress)
            result.timings["full_render_s"] = time.perf_counter() - t0
            result.files = result.files | {"mp4": path}     # a new dict: readers never see one change
            return path

        return result.cached(("full video",), make)

    @staticmethod
    def shown_video(result: Result) -> Path:
        """The video to show for a result: its antialiased MP4 once rendered (a request answered
        from an earlier identical one), else its preview."""
        full = result.peek(("full video",))
        return full if full is not None else result.files.get("preview", result.files.get("mp4"))

    def skeleton_figure(self, result: Result):
        """The 3D view, ready for gr.Plot: built and serialised as plain dicts, as plotly's
        objects (a few hundred validated frames and steps) cost most of a second."""
        from salad.render import skeleton_figure_spec

        return result.cached(("skeleton",), lambda: plot_data(frames_to_restyle_slider(
            skeleton_figure_spec(result.motion.joints, fps=result.motion.fps))))

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

    def word_video(self, result: Result, req: AttentionRequest, progress: StageProgress = quiet) -> Path:
        """The skeleton video with joints tinted by one word's attention."""
        from salad.render import render_video

        def make() -> Path:
            self.refine_feet(result, progress)
            word = result.motion.attention.words[req.word]
            tint = word_tint(self.aggregate(result, req)[req.word])
            name = f"{file_stem(result.request)}_word{req.word}-{re.sub(r'[^a-z0-9]+', '', word)[:16]}" \
                   f"_L{'-'.join(map(str, req.layers))}_s{req.steps[0] + 1}-{req.steps[1]}.mp4"
            return render_video(result.motion.joints, result.folder / name, fps=result.motion.fps,
                                title=result.motion.text, tint=tint, tint_label=f"“{word}”",
                                progress=lambda i, n: progress("rendering", i, n))

        return result.cached(("video", req.word, req.layers, req.steps), make)

    # ------------------------------------------------------------ editing
    def edit(self, session: Session, req: EditRequest, progress: StageProgress = quiet) -> Result:
        """Run one edit (source and edited branches in one batched sampling), save both motions
        and preview them side by side; it becomes the session's latest edit."""
        reused = session.reuse("edit", req)
        if reused is not None:
            return reused
        folder = session.new_folder()
        res, timings = self.sample_locked(req.steps, progress, lambda report: self.pipe.edit(
            req.source, seed=req.seed, seconds=req.seconds, steps=req.steps, cfg=req.cfg, sampler=req.sampler,
            progress=report, foot_lock=req.foot_lock, spec=req.spec, foot_refine=False))
        # An unchanged source (same prompt, seed, length, sampling) reuses its rendered panel.
        result = Result(req, res.edited, folder, {}, timings, kind="edit", source=res.source, params=res.params)
        return self._finish(session, result, save_later(result), progress)

    def edit_word_map(self, result: Result) -> list[int]:
        """For each word of the edited prompt, the source word it corresponds to, or -1 (added)."""
        from salad.editing.align import align_words

        src, tgt = result.source.attention.words, result.motion.attention.words
        mode = result.request.mode if result.request.mode in ("swap", "refine") else "same"
        return result.cached(("word map",), lambda: align_words(src, tgt, mode))

    def edit_aggregates(self, result: Result) -> tuple[np.ndarray, np.ndarray]:
        """(words, 7, T) attention of the source and of the edited motion, all layers and steps."""
        return result.cached(("edit aggregates",), lambda: (result.source.attention.aggregate(),
                                                            result.motion.attention.aggregate()))

    def edit_focus_word(self, result: Result) -> int:
        """The edited prompt's word whose attention the edit changed: the first swapped or
        added word, else the re-weighted word, else the word whose map moved most."""
        req, words = result.request, result.motion.attention.words
        src_words = result.source.attention.words
        changed = [i for i, j in enumerate(self.edit_word_map(result)) if j < 0 or src_words[j] != words[i]]
        if changed:
            return next((i for i in changed if words[i] not in FUNCTION_WORDS), changed[0])
        if req.reweight and req.reweight[0][0] in words:
            return words.index(req.reweight[0][0])
        src, edited = self.edit_aggregates(result)
        if src.shape != edited.shape:      # different lengths: compare the shared frames
            n = min(src.shape[-1], edited.shape[-1])
            src, edited = src[..., :n], edited[..., :n]
        return int(np.abs(edited - src).sum(axis=(1, 2)).argmax())

    def edit_heatmaps(self, result: Result, word: int) -> tuple:
        """The chosen edited-prompt word's map in the source and in the edited motion, on one
        colour scale (a note instead of the source map when the word was added)."""
        from salad.render import attention_heatmap

        def make():
            src, edited = self.edit_aggregates(result)
            j = self.edit_word_map(result)[word]
            name = result.motion.attention.words[word]
            zmax = float(max(edited[word].max(), src[j].max() if j >= 0 else 0.0)) or None
            right = attention_heatmap(edited[word], name, fps=result.motion.fps, zmax=zmax)
            right.update_layout(title_text=f"edited: “{name}” → body parts")
            if j < 0:
                left = note_figure(f"“{name}” was added: the source prompt has no such word")
            else:
                left = attention_heatmap(src[j], result.source.attention.words[j], fps=result.source.fps, zmax=zmax)
                left.update_layout(title_text=f"source: “{result.source.attention.words[j]}” → body parts")
            return left, right

        return result.cached(("edit heatmaps", word), make)

    def edit_extras(self, result: Result, progress: StageProgress = quiet) -> list[Path]:
        """An edit's files beyond its motions: the edited motion's own MP4 and both attention
        maps as NPZ and PNG (made on first use)."""
        from salad.render import attention_png, render_video

        def make() -> list[Path]:
            self.refine_feet(result, progress)
            stem, folder = file_stem(result.request), result.folder
            src, edited = result.source, result.motion
            single = render_video(edited.joints, folder / f"{stem}_edited.mp4", fps=edited.fps, title=edited.text,
                                  progress=lambda i, n: progress("rendering", i, n))
            npz = _save_npz(folder / f"{stem}_attention.npz", parts=np.array(sk.BODY_PARTS.names),
                            fps=np.array(edited.fps), **attention_arrays(src.attention, "source_"),
                            **attention_arrays(edited.attention, "edited_"))
            src_agg, edited_agg = self.edit_aggregates(result)
            pngs = [attention_png(agg, words, folder / f"{stem}_attention_{which}.png", fps=edited.fps)
                    for which, agg, words in (("source", src_agg, src.attention.words),
                                              ("edited", edited_agg, edited.attention.words))]
            return [single, npz, *map(Path, pngs)]

        return result.cached(("edit extras",), make)

    def edit_downloads(self, result: Result, progress: StageProgress = quiet) -> list[Path]:
        """Every file of an edit, made where missing: the side-by-side MP4, the edited motion's
        own MP4, BVH, NPY joints and features, NPZ per motion, and both attention maps as NPZ and PNG."""
        self.full_video(result, progress)
        self.edit_extras(result, progress)
        return self.downloads(result)

    # ------------------------------------------------------------ downloads
    def downloads(self, result: Result) -> list[Path]:
        """The downloads of a result made so far, in the order the page lists them: the
        antialiased MP4 once it is rendered (never the preview), the motion files, and an edit's
        extras (edit_extras) once they are made. Nothing is rendered here."""
        files = result.files
        if result.kind == "edit":
            extras = result.peek(("edit extras",), [])
            listed = [files.get("mp4")] + extras[:1] + [files.get(k) for k in EDIT_DOWNLOADS] + extras[1:]
        else:
            listed = [files.get(k) for k in DOWNLOADS[result.kind]]
        return [p for p in listed if p is not None]

    @staticmethod
    def in_bvh_units(result: Result, paths: list[Path], units: str) -> list[Path]:
        """`paths` (downloads of `result`) with its BVH files in `units`: the files as saved, in
        centimetres, or copies in metres (*_m.bvh) written beside them on first use."""
        if units == "cm":
            return list(paths)
        swap = {}
        for key, motion in (("bvh", result.motion), ("edited_bvh", result.motion), ("source_bvh", result.source)):
            cm = result.files.get(key)
            if cm is not None and motion is not None:
                swap[cm] = result.cached(("bvh", key, units), lambda cm=cm, motion=motion: motion.save(
                    cm.with_name(f"{cm.stem}_{units}.bvh"), bvh_units=units))
        return [swap.get(p, p) for p in paths]

    # ------------------------------------------------------------ guided control
    def control(self, session: Session, req: ControlRequest, signal, progress: StageProgress = quiet) -> Result:
        """Sample a motion guided by `signal`, save it with its signal, and preview it with the
        targets (and a path on the floor) drawn; it becomes the session's latest control result."""
        reused = session.reuse("control", req)
        if reused is not None:
            return reused
        folder = session.new_folder()
        motion, timings = self.sample_locked(req.steps, progress, lambda report: self.pipe.control(
            req.prompt, signal=signal, seed=req.seed, strength=req.strength, steps=req.steps, cfg=req.cfg,
            sampler=req.sampler, progress=report, foot_lock=req.foot_lock, foot_refine=False))
        stem = file_stem(req)
        signal_file = file_writer.submit(lambda: {"signal": _save_npz(
            folder / f"{stem}_control.npz", targets=signal.targets, mask=signal.mask, fps=np.array(motion.fps))})
        result = Result(req, motion, folder, {}, timings, kind="control", signal=signal)
        return self._finish(session, result, [*save_later(result), signal_file], progress)

    def control_figure(self, result: Result):
        sig, m = result.signal, result.motion
        return result.cached(("top view",), lambda: control_top_view(
            sig.targets[:m.frames], sig.mask[:m.frames], m.joints))
