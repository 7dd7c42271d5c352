"""The Real motion tab: edit a recorded motion (an uploaded BVH / NPY file or a test clip of a
dataset build) by text. The motion is inverted under a prompt describing it, then edited as in
the Edit tab; the input, its reconstruction and the edit play side by side."""
from __future__ import annotations

from dataclasses import dataclass

import gradio as gr

from salad.models.text import split_words
from salad.pipeline import MAX_PROMPT_CHARS

from ..real_edit import edit_difference, reconstruction_error_m
from ..session import Result
from ..settings import (
    DEFAULT_CFG, DEFAULT_REWEIGHT, DEFAULT_STEPS, MAX_CFG, MAX_REWEIGHT, MAX_STEPS, MAX_UPLOAD_BYTES,
)
from .edit_panel import MIRROR_CHOICES, MODE_HELP, MODES
from .generate_panel import CONTROLS_MIN_WIDTH, RESULTS_MIN_WIDTH, bvh_units_dropdown, foot_lock_checkbox
from .summaries import MIRROR_NAMES, MODE_NAMES, escape_md, foot_lock_line, quoted, warnings_block

INTRO = ("Edit a recorded motion by text. Describe the motion as it is (the source prompt): it is encoded and "
         "inverted under that prompt, so that sampling it back gives the motion again, and the edit then changes "
         "the attention between words and body parts along the same path.")
CLIPS_HINT = ("No test clips are offered: start the studio with `--clips DIR` on a dataset build "
              "(`salad data build --source bandai --input … --out data/bandai-hml`) to pick one here.")
INVERSIONS = [("negative prompt (closest, fastest)", "negative"), ("plain DDIM (drifts away)", "ddim"),
              ("null-text (about 13× slower)", "null_text"), ("fixed point (about 3× slower)", "fixed_point")]
DEFAULT_MODE = "mirror"
DEFAULT_SOURCE = "a person waves their left hand"
INVERSION_NAMES = dict((value, label.split(" (")[0]) for label, value in INVERSIONS)
KIND_NAMES = {"bvh": "BVH", "joints": "joints", "features": "features", "clip": "test clip"}


@dataclass
class RealPanel:
    upload: gr.File
    clip: gr.Dropdown
    source: gr.Textbox
    mode: gr.Radio
    mode_help: gr.Markdown
    target: gr.Textbox
    reweight_word: gr.Dropdown
    reweight_scale: gr.Slider
    mirror: gr.Radio
    inversion: gr.Radio
    steps: gr.Slider
    cfg: gr.Slider
    foot_lock: gr.Checkbox
    button: gr.Button
    video: gr.Video
    summary: gr.Markdown
    downloads: gr.File
    bvh_units: gr.Dropdown

    @property
    def inputs(self) -> list:
        return [self.upload, self.clip, self.source, self.mode, self.target, self.reweight_word, self.reweight_scale,
                self.mirror, self.inversion, self.steps, self.cfg, self.foot_lock]


def build_real_panel(clip_choices: list[tuple[str, str]]) -> RealPanel:
    """The tab's components; the clip picker only when a dataset build offers clips."""
    gr.Markdown(INTRO)
    with gr.Row(equal_height=False):
        with gr.Column(scale=2, min_width=CONTROLS_MIN_WIDTH):
            upload = gr.File(label=f"Upload a motion: .bvh, or .npy joints (T, 22, 3) in metres or features (T, 263); "
                                   f"at most {MAX_UPLOAD_BYTES // 1000} kB",
                             file_count="single", file_types=[".bvh", ".npy"], type="filepath",
                             elem_id="real-upload")
            clip = gr.Dropdown([("none", "")] + clip_choices, value="", label="or a test clip of the dataset",
                               info="picking one fills in its caption as the source prompt",
                               visible=bool(clip_choices), elem_id="real-clip")
            gr.Markdown(CLIPS_HINT, visible=not clip_choices, elem_id="real-clips-hint")
            source = gr.Textbox(label="Source prompt: what the motion shows", lines=2, max_lines=4,
                                max_length=MAX_PROMPT_CHARS, value=DEFAULT_SOURCE, elem_id="real-source")
            mode = gr.Radio(MODES, value=DEFAULT_MODE, label="Edit", elem_id="real-mode")
            mode_help = gr.Markdown(MODE_HELP[DEFAULT_MODE], elem_id="real-mode-help")
            target = gr.Textbox(label="Target prompt", lines=2, max_lines=4, max_length=MAX_PROMPT_CHARS, value="",
                                visible=False, elem_id="real-target")
            with gr.Row():
                words = dict.fromkeys(split_words(DEFAULT_SOURCE))
                reweight_word = gr.Dropdown([("none", "")] + [(w, w) for w in words], value="",
                                            label="Word to re-weight", scale=1, min_width=140,
                                            elem_id="real-reweight-word",
                                            info="a word of the prompt being edited; optional with swap/refine")
                reweight_scale = gr.Slider(-MAX_REWEIGHT, MAX_REWEIGHT, value=DEFAULT_REWEIGHT, step=0.1, scale=2,
                                           label="s: its attention scale", elem_id="real-reweight-scale",
                                           info="1 = unchanged, 0 = ignored, < 0 = inverted")
            mirror = gr.Radio(MIRROR_CHOICES, value="all", label="Mirror (also with any other edit)",
                              elem_id="real-mirror")
            with gr.Accordion("Inversion and sampling", open=False):
                inversion = gr.Radio(INVERSIONS, value="negative", label="Inversion", elem_id="real-inversion")
                steps = gr.Slider(1, MAX_STEPS, value=DEFAULT_STEPS, step=1, label="Diffusion steps (DDIM)",
                                  info="the inversion and the edit take as many each", elem_id="real-steps")
                cfg = gr.Slider(0.0, MAX_CFG, value=DEFAULT_CFG, step=0.5, label="Guidance (CFG scale)",
                                elem_id="real-cfg")
                foot_lock = foot_lock_checkbox("real-foot-lock")
            button = gr.Button("Edit the motion", variant="primary", elem_id="real-button")
        with gr.Column(scale=3, min_width=RESULTS_MIN_WIDTH):
            gr.Markdown("**Input, reconstruction and edit, in sync**", elem_classes="video-caption")
            video = gr.Video(label="Input, reconstruction and edit", show_label=False, autoplay=True, loop=True,
                             interactive=False, elem_id="real-video")
            summary = gr.Markdown(elem_id="real-summary")
            bvh_units = bvh_units_dropdown("real-bvh-units")
            downloads = gr.File(label="Downloads: edited BVH, NPY joints and features, side-by-side MP4",
                                file_count="multiple", interactive=False, elem_id="real-downloads")
    return RealPanel(upload, clip, source, mode, mode_help, target, reweight_word, reweight_scale, mirror,
                     inversion, steps, cfg, foot_lock, button, video, summary, downloads, bvh_units)


def real_markdown(result: Result) -> str:
    """What was edited and how, the reconstruction's error, where the edit changed the motion,
    and how long each part took."""
    r, rec = result.request, result.source
    what = [f"**{MODE_NAMES[r.mode]}**"]
    weights = [f"{quoted(w)} × {s:g}" for w, s in r.reweight]
    if r.mode in ("swap", "refine"):
        what[0] += f" to {quoted(r.target)}"
    elif r.mode == "reweight":
        what[0] += " " + weights.pop(0)
    elif r.mirror:
        what[0] += f" {MIRROR_NAMES[r.mirror]}"
    what += [f"re-weighted {w}" for w in weights]
    if r.mirror and r.mode != "mirror":
        what.append(f"mirrored {MIRROR_NAMES[r.mirror]}")
    params = result.params
    trimmed = params.get("trimmed_from_frames")
    length = f"{rec.seconds:.1f} s ({rec.frames} frames"
    length += f", the first of {trimmed} frames)" if trimmed else ")"
    diff = edit_difference(result)
    part, change = diff.most_changed
    t = result.timings
    waited = f", waited {t['wait_s']:.1f} s" if t.get("wait_s", 0) > 0.5 else ""
    return warnings_block(rec, result.motion) + (f"{' · '.join(what)} of {KIND_NAMES[r.input_kind]} {quoted(r.input_name)} described as "
            f"{quoted(r.source)}: {length}, {INVERSION_NAMES[r.inversion]} inversion, {r.steps} DDIM steps, "
            f"CFG {r.cfg:g}.  \n"
            f"**Reconstruction error (MPJPE): {100 * reconstruction_error_m(result):.1f} cm** against the input. "
            f"Most changed by the edit: **{escape_md(part)}** ({100 * change:.0f} cm on average, pelvis-relative); "
            f"the pelvis path moved {100 * diff.root_change_m:.0f} cm on average.  \n"
            + foot_lock_line(result.motion)
            + f"Inverted in {t['inversion_s']:.1f} s, edited in {t['edit_s']:.1f} s, "
            f"rendered in {t['render_s']:.1f} s{waited}.")
