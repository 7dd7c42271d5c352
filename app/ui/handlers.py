"""Event handlers: turn page/API values into Studio calls and Studio results into component
updates. Every failure reaches the user as a gr.Error with a readable message; nothing a
request sends can take the server down."""

import functools
import html
import logging
from collections import Counter

import gradio as gr

from .. import controls, real_edit, real_input
from ..figures import control_top_view, note_figure
from ..session import Result, Session
from ..settings import DEFAULT_TAU
from ..studio import Studio, refinement_pending
from ..validation import (
    AttentionRequest, control_signal, parse_attention, parse_bvh_units, parse_control, parse_edit, parse_generate,
    parse_real_edit, parse_word,
)
from .edit_panel import MODE_HELP
from .control_panel import UPLOAD_HELP
from .generate_panel import steps_for
from .real_panel import real_markdown, sampler_updates
from .summaries import control_markdown, edit_markdown, summary_markdown

log = logging.getLogger("salad.studio")
NO_MOTION = "generate a motion first: the attention maps belong to the last generated motion"
NO_MOTION_TO_EDIT = "generate a motion first: the Edit tab takes its prompt, length, seed and sampling"
NO_EDIT = "run an edit first: the maps belong to the last edit"
NO_RESULT = {"generate": "generate a motion first: its video is rendered after it",
             "edit": "run an edit first: its video is rendered after it",
             "control": "generate with control first: its video is rendered after it"}
TARGET_LABELS = {"swap": "Target prompt (the source with words replaced)",
                 "refine": "Target prompt (the source with words added)"}


def guarded(fn):
    """Report ValueErrors (bad input) as they are and anything else as an internal error,
    logged with its traceback."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except gr.Error:
            raise
        except ValueError as exc:
            raise gr.Error(str(exc), title="Invalid input", print_exception=False) from None
        except Exception as exc:
            log.exception("%s failed", fn.__name__)
            raise gr.Error(f"the server could not finish this request ({type(exc).__name__}); "
                           "it has been logged, please try again", print_exception=False) from None
    return wrapper


def _gr_progress(progress: gr.Progress):
    def report(stage: str, done: int, total: int) -> None:
        progress((done, total), desc=stage, unit="frames" if stage == "rendering" else "steps")
    return report


def word_choices(words: list[str]) -> list[tuple[str, int]]:
    """Radio choices (label, word index); repeated words get a number so each chip is unique."""
    seen: Counter = Counter()
    totals = Counter(words)
    out = []
    for i, w in enumerate(words):
        seen[w] += 1
        out.append((f"{w} ({seen[w]})" if totals[w] > 1 else w, i))
    return out


class Handlers:
    """The functions the page's events call; one instance per app."""

    def __init__(self, studio: Studio, clips: "real_input.ClipLibrary | None" = None):
        self.studio = studio
        self.clips = clips          # test clips offered in the Real motion tab

    def _current(self, state, request: gr.Request) -> Result:
        if not isinstance(state, Session) or state.current is None:
            raise ValueError(NO_MOTION)
        self.studio.session(state, request.session_hash)     # marks the session as in use
        return state.current

    def _note_upload(self, upload, request: gr.Request | None) -> None:
        """An uploaded file a request used goes when its session ends."""
        path = upload.get("path") if isinstance(upload, dict) else upload
        if isinstance(path, str) and request is not None and request.session_hash:
            self.studio.workspace.note_upload(request.session_hash, path)

    @staticmethod
    def length_mode(auto_length):
        return gr.Slider(interactive=not bool(auto_length))

    @staticmethod
    def sampler_steps(sampler):
        """The sampler changed: the steps slider goes to its default (salad.pipeline.DEFAULT_STEPS)."""
        return steps_for(sampler)

    @staticmethod
    def real_sampler(sampler):
        """As sampler_steps, for the Real motion tab, whose inversion and seed follow the sampler too."""
        return sampler_updates(sampler)

    def generate(self, prompt, auto_length, seconds, seed, steps, cfg, sampler, foot_lock, state,
                 request: gr.Request, progress=gr.Progress()):
        req = parse_generate(self.studio.pipe, prompt, auto_length, seconds, seed, steps, cfg, sampler, foot_lock)
        session = self.studio.session(state, request.session_hash)
        result = self.studio.generate(session, req, _gr_progress(progress))
        maps = result.motion.attention
        files = [str(p) for p in self.studio.downloads(result)]
        return (
            session,
            str(self.studio.shown_video(result)),
            self.studio.skeleton_figure(result),
            summary_markdown(result),
            files,
            gr.Radio(choices=word_choices(maps.words), value=None, label="Word"),
            gr.CheckboxGroup(choices=[(f"layer {l}", l) for l in maps.layers], value=list(maps.layers)),
            gr.Slider(minimum=1, maximum=maps.steps, value=1),
            gr.Slider(minimum=1, maximum=maps.steps, value=maps.steps),
            None,
            None,
        )

    def edit_generated(self, state, request: gr.Request):
        """The Edit tab, shown, takes the last generated motion's prompt (as source and target), length, seed and
        sampling: its edits then start from that very motion, whose sampling the pipeline replays
        instead of running the source branch again."""
        result = state.latest("generate") if isinstance(state, Session) else None
        if result is None:
            raise ValueError(NO_MOTION_TO_EDIT)
        self.studio.session(state, request.session_hash)
        r = result.request
        auto = r.seconds is None
        seconds = gr.Slider(interactive=False) if auto else gr.Slider(value=r.seconds, interactive=True)
        return (gr.Tabs(selected="edit"), r.prompt, r.prompt, auto, seconds, r.seed, r.steps, r.cfg, r.sampler,
                r.foot_lock)

    def _full_video(self, kind: str, units, state, request: gr.Request, progress):
        """The session's latest `kind` result's antialiased MP4 (rendered now unless it was before)
        and its downloads relisted with it, BVH files in `units`."""
        units = parse_bvh_units(units)
        result = state.latest(kind) if isinstance(state, Session) else None
        if result is None:
            raise ValueError(NO_RESULT[kind])
        self.studio.session(state, request.session_hash)
        video = self.studio.full_video(result, _gr_progress(progress))
        return str(video), [str(p) for p in self.studio.in_bvh_units(result, self.studio.downloads(result), units)]

    def _full_video_and_views(self, kind: str, views, units, state, request: gr.Request, progress) -> tuple:
        """_full_video, then each of `views` (result -> one of the panel's views of the motion) when its
        planted feet were refined on the way (Studio.refine_feet), else gr.skip(): a view sent again is
        drawn again."""
        result = state.latest(kind) if isinstance(state, Session) else None
        pending = result is not None and refinement_pending(result)
        video, files = self._full_video(kind, units, state, request, progress)
        return video, files, *(view(result) if pending else gr.skip() for view in views)

    def generate_video(self, units, state, request: gr.Request, progress=gr.Progress()):
        return self._full_video_and_views("generate", (self.studio.skeleton_figure, summary_markdown),
                                          units, state, request, progress)

    def edit_video(self, units, state, request: gr.Request, progress=gr.Progress()):
        return self._full_video_and_views("edit", (lambda r: edit_markdown(r, self.studio.edit_word_map(r)),),
                                          units, state, request, progress)

    def control_video(self, units, state, request: gr.Request, progress=gr.Progress()):
        return self._full_video_and_views("control", (self.studio.control_figure, control_markdown),
                                          units, state, request, progress)

    def _request(self, result: Result, word, layers, first_step, last_step) -> AttentionRequest:
        return parse_attention(result.motion.attention, word, layers, first_step, last_step)

    def attention(self, word, layers, first_step, last_step, state, request: gr.Request):
        result = self._current(state, request)
        req = self._request(result, word, layers, first_step, last_step)
        heatmap = self.studio.word_heatmap(result, req) if req.word is not None else None
        files = [str(p) for p in self.studio.attention_files(result, req)]
        return heatmap, self.studio.overview(result, req), files

    def attention_video(self, word, layers, first_step, last_step, state, request: gr.Request,
                        progress=gr.Progress()):
        result = self._current(state, request)
        req = self._request(result, word, layers, first_step, last_step)
        if req.word is None:
            return None
        return str(self.studio.word_video(result, req, _gr_progress(progress)))

    # ------------------------------------------------------------ editing
    def _word_picker(self, source, mode, target, current, keep: bool = True):
        """The re-weighting picker: the words of the prompt being edited (the target with
        swap/refine). A valid current word stays when `keep`; reweight mode always has one."""
        text = target if mode in ("swap", "refine") and isinstance(target, str) and target.strip() else source
        words = list(dict.fromkeys(self.studio.pipe.text_encoder.split_words(text))) if isinstance(text, str) else []
        if keep and current in words:
            value = current
        else:
            value = words[-1] if mode == "reweight" and words else ""
        choices = ([] if mode == "reweight" else [("none", "")]) + [(w, w) for w in words]
        return gr.Dropdown(choices=choices, value=value if value or mode != "reweight" else None)

    def edit_mode(self, mode, mirror, source, target, current):
        """Show the controls the chosen strategy uses, with its default τ; mirror mode starts on
        arms and legs and without re-weighting (which composes with swap and refine)."""
        if mode not in MODE_HELP:
            raise ValueError(f"edit mode must be one of {', '.join(MODE_HELP)}, got {mode!r}")
        with_target = mode in ("swap", "refine")
        return (MODE_HELP[mode],
                gr.Textbox(visible=with_target, label=TARGET_LABELS.get(mode, "Target prompt")),
                gr.Slider(visible=with_target, value=DEFAULT_TAU.get(mode, 0.0)),
                gr.Radio(value="all" if mode == "mirror" and mirror in (None, "none") else mirror),
                self._word_picker(source, mode, target, current, keep=mode != "mirror"))

    def edit_words(self, source, mode, target, current):
        """The prompt changed: refill the re-weighting picker."""
        return self._word_picker(source, mode, target, current)

    def _edit_result(self, state, request: gr.Request) -> Result:
        result = state.latest("edit") if isinstance(state, Session) else None
        if result is None:
            raise ValueError(NO_EDIT)
        self.studio.session(state, request.session_hash)
        return result

    def edit(self, source, mode, target, tau, reweight_word, reweight_scale, mirror, self_inject, hold, auto_length,
             seconds, seed, steps, cfg, sampler, foot_lock, state, request: gr.Request, progress=gr.Progress()):
        req = parse_edit(self.studio.pipe, source, mode, target, tau, reweight_word, reweight_scale, mirror,
                         self_inject, hold, auto_length, seconds, seed, steps, cfg, sampler, foot_lock)
        session = self.studio.session(state, request.session_hash)
        result = self.studio.edit(session, req, _gr_progress(progress))
        focus = self.studio.edit_focus_word(result)
        left, right = self.studio.edit_heatmaps(result, focus)
        files = [str(p) for p in self.studio.downloads(result)]
        return (session, str(self.studio.shown_video(result)), edit_markdown(result, self.studio.edit_word_map(result)),
                gr.Radio(choices=word_choices(result.motion.attention.words), value=focus,
                         label="Word: its attention before and after the edit"),
                left, right, files)

    def edit_files(self, state, request: gr.Request, progress=gr.Progress()):
        result = self._edit_result(state, request)
        return [str(p) for p in self.studio.edit_downloads(result, _gr_progress(progress))]

    def edit_attention(self, word, state, request: gr.Request):
        result = self._edit_result(state, request)
        index = parse_word(result.motion.attention.words, word)
        if index is None:
            raise ValueError("choose a word of the edited prompt")
        return self.studio.edit_heatmaps(result, index)

    # ------------------------------------------------------------ guided control
    @staticmethod
    def control_task(task):
        """Show the inputs the chosen kind of targets needs."""
        if task not in controls.TASKS:
            raise ValueError(f"task must be one of {', '.join(controls.TASKS)}, got {task!r}")
        return (gr.Group(visible=task == "path"), gr.Group(visible=task in UPLOAD_HELP),
                UPLOAD_HELP.get(task, ""), gr.Textbox(visible=task == "inbetween"))

    def _signal(self, task, preset, seconds, speed, upload, example, keyframes, state):
        base = state.current if isinstance(state, Session) else None
        return control_signal(self.studio.pipe, task, preset, seconds, speed, upload, example, keyframes, base=base,
                              upload_root=self.studio.workspace.gradio_cache, examples_dir=self.studio.control_examples)

    def control_preview(self, task, preset, seconds, speed, upload, example, keyframes, state,
                        request: gr.Request = None):
        """The targets seen from above, or why there are none yet (never an error toast:
        the inputs may still be half filled in)."""
        self._note_upload(upload, request)
        try:
            signal, _, _ = self._signal(task, preset, seconds, speed, upload, example, keyframes, state)
        except ValueError as exc:
            return note_figure(html.escape(str(exc)[:160]), height=320)
        return control_top_view(signal.targets, signal.mask)

    def control(self, prompt, task, preset, seconds, speed, upload, example, keyframes, strength, seed, steps, cfg,
                foot_lock, sampler, state, request: gr.Request, progress=gr.Progress()):
        base = state.current if isinstance(state, Session) else None
        self._note_upload(upload, request)
        req, signal = parse_control(self.studio.pipe, prompt, task, preset, seconds, speed, upload, example, keyframes,
                                    strength, seed, steps, cfg, foot_lock, sampler, base=base,
                                    upload_root=self.studio.workspace.gradio_cache,
                                    examples_dir=self.studio.control_examples)
        session = self.studio.session(state, request.session_hash)
        result = self.studio.control(session, req, signal, _gr_progress(progress))
        files = [str(p) for p in self.studio.downloads(result)]
        return (session, str(self.studio.shown_video(result)), self.studio.control_figure(result),
                control_markdown(result), files)

    # ------------------------------------------------------------ real motions
    def real_mode(self, mode, mirror, source, target, current):
        """As edit_mode, for the Real motion tab (which keeps τ at the mode's default)."""
        help_text, target_box, _tau, mirror_radio, words = self.edit_mode(mode, mirror, source, target, current)
        return help_text, target_box, mirror_radio, words

    def real_clip(self, clip):
        """A test clip was picked: its caption becomes the source prompt and an upload is dropped."""
        if clip in (None, "", "none"):
            return gr.Textbox(), gr.File()
        if self.clips is None:
            raise ValueError("no test clips are offered: start the studio with --clips DIR (a dataset build)")
        return self.clips.caption(clip), None

    def real_upload(self, upload=None, request: gr.Request = None):
        """A file was uploaded: it is read now, so that a file the edit could not use is reported at
        once rather than on pressing Edit, and it replaces a picked test clip."""
        self._note_upload(upload, request)
        up = real_input.upload_path(upload, self.studio.workspace.gradio_cache)
        if up is not None:
            real_input.read_upload(up.path, up.name)
        return ""

    def edit_real(self, upload, clip, source, mode, target, reweight_word, reweight_scale, mirror, inversion, steps,
                  cfg, foot_lock, sampler, seed, state, request: gr.Request, progress=gr.Progress()):
        self._note_upload(upload, request)
        req, motion = parse_real_edit(self.studio.pipe, upload, clip, source, mode, target, reweight_word,
                                      reweight_scale, mirror, inversion, steps, cfg, foot_lock, sampler, seed,
                                      upload_root=self.studio.workspace.gradio_cache, clips=self.clips)
        session = self.studio.session(state, request.session_hash)
        result = real_edit.edit_real(self.studio, session, req, motion, _gr_progress(progress))
        files = [str(p) for p in self.studio.downloads(result)]
        return session, str(result.files["mp4"]), real_markdown(result), files

    # ------------------------------------------------------------ downloads
    def bvh_units(self, kind: str):
        """The handler that lists the downloads of the session's latest `kind` result with its BVH
        files in the chosen units (left as they are while there is no such result)."""
        def handler(units, state, request: gr.Request):
            units = parse_bvh_units(units)
            result = state.latest(kind) if isinstance(state, Session) else None
            if result is None:
                return gr.File()
            self.studio.session(state, request.session_hash)
            return [str(p) for p in self.studio.in_bvh_units(result, self.studio.downloads(result), units)]
        handler.__name__ = f"bvh_units_{kind}"
        return handler

    def unload(self, request: gr.Request) -> None:
        # The tab is gone: its files (with Gradio's served copies and its uploads) go now; the
        # session's state follows when Gradio drops it.
        try:
            self.studio.workspace.remove_session(request.session_hash)
        except Exception:   # a failed clean-up is retried by the janitor
            log.exception("removing the files of a closed session failed")


def guard_all(handlers: Handlers) -> dict:
    """The handlers wrapped by `guarded`, by name."""
    names = ("length_mode", "sampler_steps", "real_sampler", "generate", "generate_video", "attention",
             "attention_video", "edit_generated", "edit_mode", "edit_words", "edit", "edit_video", "edit_files",
             "edit_attention", "control_task", "control_preview", "control", "control_video", "real_mode",
             "real_clip", "real_upload", "edit_real")
    units = {f"bvh_units_{kind}": guarded(handlers.bvh_units(kind)) for kind in ("generate", "edit", "control", "real")}
    return {n: guarded(getattr(handlers, n)) for n in names} | units | {"unload": handlers.unload}
