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
from ..settings import DEFAULT_CFG, DEFAULT_REWEIGHT, MAX_CFG, MAX_REWEIGHT, MAX_SEED, MAX_UPLOAD_BYTES
from .edit_panel import MIRROR_CHOICES, MODE_HELP, MODES
from .generate_panel import (
    CONTROLS_MIN_WIDTH, RESULTS_MIN_WIDTH, bvh_units_dropdown, foot_lock_checkbox, guided_sampler, steps_for,
    steps_slider,
)
from .summaries import MIRROR_NAMES, MODE_NAMES, escape_md, foot_lock_line, quoted, sampling_text, warnings_block

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
STEPS_INFO = {"ddim": "the inversion and the edit take as many each",
              "consistency": "the student edits the encoded motion directly: no inversion"}
SEED_INFO = "the student's noise (an inversion needs none)"


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
    sampler: gr.Radio
    seed: gr.Number
    button: gr.Button
    video: gr.Video
    summary: gr.Markdown
    downloads: gr.File
    bvh_units: gr.Dropdown

    @property
    def inputs(self) -> list:
        # new inputs go last: API clients call the event with positional arguments
        return [self.upload, self.clip, self.source, self.mode, self.target, self.reweight_word, self.reweight_scale,
                self.mirror, self.inversion, self.steps, self.cfg, self.foot_lock, self.sampler, self.seed]


def sampler_updates(sampler) -> tuple:
    """The sampler changed: the steps slider (its default, range and note), the inversion choice
    (which the student does without) and the seed (which only the student uses)."""
    if sampler not in STEPS_INFO:
        return gr.Slider(), gr.Radio(), gr.Number()
    student = sampler == "consistency"
    return steps_for(sampler, info=STEPS_INFO[sampler]), gr.Radio(interactive=not student), gr.Number(visible=student)


def build_real_panel(clip_choices: list[tuple[str, str]], samplers=("ddim", "dpm"),
                     sampler: str = "ddim") -> RealPanel:
    """The tab's components; the clip picker only when a dataset build offers clips, the sampler
    choice only when the model has a distilled student (`samplers`: app.studio.offered_samplers)."""
    choices, sampler, with_student = guided_sampler(samplers, sampler)
    student = sampler == "consistency"
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
                sampler_radio = gr.Radio(choices, value=sampler, label="Sampler", visible=with_student,
                                         elem_id="real-sampler")
                inversion = gr.Radio(INVERSIONS, value="negative", label="Inversion", interactive=not student,
                                     elem_id="real-inversion")
                steps = steps_slider(sampler, "Diffusion steps" if with_student else "Diffusion steps (DDIM)",
                                     info=STEPS_INFO[sampler], elem_id="real-steps")
                seed = gr.Number(value=0, precision=0, minimum=0, maximum=MAX_SEED, label="Seed", info=SEED_INFO,
                                 visible=student, elem_id="real-seed")
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
                     inversion, steps, cfg, foot_lock, sampler_radio, seed, button, video, summary, downloads,
                     bvh_units)


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
    if r.sampler == "consistency":      # the student edits the encoded motion: no inversion ran
        how = f"no inversion, {sampling_text(r.sampler, r.steps)}, seed {r.seed}"
        took = f"Edited in {t['edit_s']:.1f} s"
    else:
        how = f"{INVERSION_NAMES[r.inversion]} inversion, {sampling_text(r.sampler, r.steps)}"
        took = f"Inverted in {t['inversion_s']:.1f} s, edited in {t['edit_s']:.1f} s"
    return warnings_block(rec, result.motion) + (
            f"{' · '.join(what)} of {KIND_NAMES[r.input_kind]} {quoted(r.input_name)} described as "
            f"{quoted(r.source)}: {length}, {how}, CFG {r.cfg:g}.  \n"
            f"**Reconstruction error (MPJPE): {100 * reconstruction_error_m(result):.1f} cm** against the input. "
            f"Most changed by the edit: **{escape_md(part)}** ({100 * change:.0f} cm on average, pelvis-relative); "
            f"the pelvis path moved {100 * diff.root_change_m:.0f} cm on average.  \n"
            + foot_lock_line(result.motion)
            + f"{took}, rendered in {t['render_s']:.1f} s{waited}.")
