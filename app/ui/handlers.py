"""Event handlers: turn page/API values into Studio calls and Studio results into component
updates. Every failure reaches the user as a gr.Error with a readable message; nothing a
request sends can take the server down."""

import functools
import logging
from collections import Counter

import gradio as gr

from ..session import Result, Session
from ..studio import Studio
from ..validation import AttentionRequest, parse_attention, parse_generate

log = logging.getLogger("salad.studio")
NO_MOTION = "generate a motion first: the attention maps belong to the last generated motion"


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


def escape_md(text: str) -> str:
    return "".join("\\" + c if c in "\\`*_{}[]()#+-.!|<>~" else c for c in text)


def summary_markdown(result: Result) -> str:
    r, m, t = result.request, result.motion, result.timings
    length = "automatic length" if r.seconds is None else f"{r.seconds:g} s requested"
    waited = f", waited {t['wait_s']:.1f} s" if t.get("wait_s", 0) > 0.5 else ""
    return (f"**“{escape_md(r.prompt)}”** — {m.seconds:.1f} s ({m.frames} frames, {length}), seed {r.seed}, "
            f"{r.steps} {r.sampler.upper()} steps, CFG {r.cfg:g}. Sampled in {t['sample_s']:.1f} s, "
            f"rendered in {t['render_s']:.1f} s{waited}.")


class Handlers:
    """The functions the page's events call; one instance per app."""

    def __init__(self, studio: Studio):
        self.studio = studio

    def _current(self, state, request: gr.Request) -> Result:
        if not isinstance(state, Session) or state.current is None:
            raise ValueError(NO_MOTION)
        self.studio.session(state, request.session_hash)     # marks the session as in use
        return state.current

    @staticmethod
    def length_mode(auto_length):
        return gr.Slider(interactive=not bool(auto_length))

    def generate(self, prompt, auto_length, seconds, seed, steps, cfg, sampler, state,
                 request: gr.Request, progress=gr.Progress()):
        req = parse_generate(self.studio.pipe, prompt, auto_length, seconds, seed, steps, cfg, sampler)
        session = self.studio.session(state, request.session_hash)
        result = self.studio.generate(session, req, _gr_progress(progress))
        maps = result.motion.attention
        files = [str(result.files[k]) for k in ("mp4", "bvh", "npy", "npz")]
        return (
            session,
            str(result.files["mp4"]),
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

    def unload(self, request: gr.Request) -> None:
        # The tab is gone: its files go now; the session's state follows when Gradio drops it.
        try:
            self.studio.workspace.remove_session(request.session_hash)
        except Exception:   # a failed clean-up is retried by the janitor
            log.exception("removing the files of a closed session failed")


def guard_all(handlers: Handlers) -> dict:
    """The handlers wrapped by `guarded`, by name."""
    names = ("length_mode", "generate", "attention", "attention_video")
    return {n: guarded(getattr(handlers, n)) for n in names} | {"unload": handlers.unload}
