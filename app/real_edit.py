"""Editing real motions in the studio: an input (app.real_input) inverted and edited by text
through `Pipeline.edit_real`, then saved and rendered next to the input and its reconstruction."""
from __future__ import annotations

import re
import shutil

from .compare import Difference, motion_difference
from .real_input import RealInput
from .session import Result, Session
from .studio import StageProgress, Studio, file_writer, quiet, save_motion, slug
from .validation import RealEditRequest


# ------------------------------------------------------------------ the edit

def reconstruction_error_m(result: Result) -> float:
    """A real edit's reconstruction error against its input (pelvis-aligned MPJPE, as the model saw it)."""
    return float(result.source.info["mpjpe_m"])


def edit_difference(result: Result) -> Difference:
    """Where a real edit changed the reconstruction."""
    return result.cached(("difference",), lambda: motion_difference(result.source.joints, result.motion.joints))


def _without_type(name: str) -> str:
    return re.sub(r"\.(bvh|npy)$", "", name, flags=re.IGNORECASE)


def file_stem(req: RealEditRequest) -> str:
    """The input's name and what was done to it, safe as a file name."""
    return f"{slug(_without_type(req.input_name), 32) or 'motion'}_{req.mode}"


def _stages(progress: StageProgress, steps: int, sampler: str = "ddim"):
    """edit_real reports (done, 2 * steps): the inversion first, then the edit; with the student
    (no inversion) (done, steps) of the edit alone."""
    def report(done: int, total: int) -> None:
        if sampler == "consistency":
            progress("editing", done, steps)
        elif done < steps:
            progress("inverting", done, steps)
        else:
            progress("editing", done - steps, steps)
    return report


def _input_label(name: str, limit: int = 32) -> str:
    stem = _without_type(name)
    return f"input: {stem if len(stem) <= limit else stem[:limit - 3] + '...'}"


def edit_real(studio: Studio, session: Session, req: RealEditRequest, motion: RealInput,
              progress: StageProgress = quiet) -> Result:
    """Invert and edit `motion` (under the model lock), or edit it with the distilled student
    (req.sampler "consistency", no inversion), save the edited motion (BVH, NPY joints and
    features) and render input, reconstruction and edit side by side."""
    from salad.render import render_side_by_side

    reused = session.reuse("real", req)
    if reused is not None:
        return reused
    folder = session.new_folder()
    try:
        if req.sampler == "consistency":    # the student edits the encoded motion: no inversion applies
            how = dict(sampler="consistency", seed=req.seed)
        else:
            how = dict(sampler="ddim", inversion=req.inversion)
        res, timings = studio.sample_locked(req.steps, progress, lambda _report: studio.pipe.edit_real(
            motion.motion, req.source, steps=req.steps, cfg=req.cfg, spec=req.spec, trim=True,
            progress=_stages(progress, req.steps, req.sampler), foot_lock=req.foot_lock, **how))
        timings["edit_s"] = float(res.params["edit_seconds"])
        if "inversion_seconds" in res.params:
            timings["inversion_s"] = float(res.params["inversion_seconds"])
        stem, edited = file_stem(req), res.edited
        saved = file_writer.submit(save_motion, edited, folder, f"{stem}_edited")
        # the input as it came, cut to the frames that were edited
        shown = motion.shown[:res.source.frames]
        labels = [_input_label(motion.name), "reconstruction", f"edited ({req.mode})"]
        mp4, timings["render_s"] = studio.rendered(progress, lambda report: render_side_by_side(
            [shown, res.source.joints, edited.joints], labels, folder / f"{stem}_side-by-side.mp4",
            fps=edited.fps, progress=report))
        files = {"mp4": mp4} | saved.result()
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    result = Result(req, res.edited, folder, files, timings, kind="real", source=res.source, given=motion,
                    params=res.params)
    session.add(result)
    return result
