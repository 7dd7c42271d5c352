"""The Control tab: a prompt plus joint targets the motion must meet (a pelvis path, a
control file, keyframes or the lower body of an earlier motion)."""
from __future__ import annotations

from dataclasses import dataclass

import gradio as gr

from salad.motion.representation import FPS
from salad.pipeline import MAX_PROMPT_CHARS, MIN_AUTO_FRAMES

from ..controls import PRESETS, TASKS, preset_signal
from ..figures import control_top_view
from ..settings import (
    DEFAULT_CFG, DEFAULT_PATH_SPEED, DEFAULT_SECONDS, DEFAULT_STRENGTH, MAX_CFG, MAX_PATH_SPEED, MAX_SEED,
    MAX_STRENGTH, MAX_UPLOAD_BYTES, SECONDS_STEP,
)
from .generate_panel import (
    CONTROLS_MIN_WIDTH, MIN_SECONDS, RESULTS_MIN_WIDTH, bvh_units_dropdown, foot_lock_checkbox, guided_sampler,
    steps_slider,
)

INTRO = ("Generate a motion that also meets joint position targets, by guiding the sampling "
         "(no retraining). Targets are in metres, Y up, the character starting at the origin facing +Z "
         "(its left is +X), 20 frames per second.")
DEFAULT_PRESET = "circle"
UPLOAD_HELP = {
    "mola": "MoLA's control format: (T, 22, 3) joint positions, joints that are all zeros are free.",
    "targets": "(T, 22, 3) joint positions with NaN marking free values, or (T, 2) pelvis x, z per frame "
               "(NaN rows free).",
}


def initial_preview(seconds: float, speed: float):
    frames = max(MIN_AUTO_FRAMES, int(round(seconds * FPS / 4)) * 4)
    signal = preset_signal(DEFAULT_PRESET, frames, speed, FPS)
    return control_top_view(signal.targets, signal.mask)


@dataclass
class ControlPanel:
    prompt: gr.Textbox
    task: gr.Radio
    path_group: gr.Group
    preset: gr.Dropdown
    seconds: gr.Slider
    speed: gr.Slider
    upload_group: gr.Group
    upload: gr.File
    example: gr.Dropdown
    upload_help: gr.Markdown
    keyframes: gr.Textbox
    strength: gr.Slider
    seed: gr.Number
    steps: gr.Slider
    cfg: gr.Slider
    foot_lock: gr.Checkbox
    sampler: gr.Radio
    button: gr.Button
    preview: gr.Plot
    video: gr.Video
    top_view: gr.Plot
    summary: gr.Markdown
    downloads: gr.File
    bvh_units: gr.Dropdown

    @property
    def inputs(self) -> list:
        return [self.prompt, self.task, self.preset, self.seconds, self.speed, self.upload, self.example,
                self.keyframes, self.strength, self.seed, self.steps, self.cfg, self.foot_lock, self.sampler]

    @property
    def path_inputs(self) -> list:
        return [self.task, self.preset, self.seconds, self.speed]


def build_control_panel(pipe, examples: list[str], samplers=("ddim", "dpm"), sampler: str = "ddim") -> ControlPanel:
    """`samplers`: those offered (app.studio.offered_samplers), `sampler` the studio's default; the
    guidance samples with DDIM or, when the model has one, the distilled student."""
    longest = max(MIN_SECONDS, float(pipe.max_seconds))
    choices, sampler, with_student = guided_sampler(samplers, sampler)
    gr.Markdown(INTRO)
    with gr.Row(equal_height=False):
        with gr.Column(scale=2, min_width=CONTROLS_MIN_WIDTH):
            prompt = gr.Textbox(label="Prompt", lines=2, max_lines=4, max_length=MAX_PROMPT_CHARS,
                                value="a person walks forward", elem_id="control-prompt")
            task = gr.Radio([(label, key) for key, label in TASKS.items()], value="path", label="Targets",
                            elem_id="control-task")
            with gr.Group(visible=True) as path_group:
                preset = gr.Dropdown([(label, key) for key, label in PRESETS.items()], value=DEFAULT_PRESET,
                                     label="Path", elem_id="control-preset")
                with gr.Row():
                    seconds = gr.Slider(MIN_SECONDS, longest, value=min(DEFAULT_SECONDS, longest), step=SECONDS_STEP,
                                        label="Seconds", elem_id="control-seconds")
                    speed = gr.Slider(0.1, MAX_PATH_SPEED, value=DEFAULT_PATH_SPEED, step=0.1, label="Speed (m/s)",
                                      elem_id="control-speed")
            with gr.Group(visible=False) as upload_group:
                upload_help = gr.Markdown(UPLOAD_HELP["mola"])
                upload = gr.File(label=f"Upload a .npy (at most {MAX_UPLOAD_BYTES // 1000} kB)", file_count="single",
                                 file_types=[".npy"], type="filepath", elem_id="control-upload")
                example = gr.Dropdown([("none", "")] + [(e, e) for e in examples], value="",
                                      label="or an installed example", visible=bool(examples),
                                      elem_id="control-example")
            keyframes = gr.Textbox(value="first, last", label="Keyframes of your last motion to keep",
                                   info="frame numbers from 0, ranges such as 0-3, 'first', 'last'",
                                   visible=False, elem_id="control-keyframes")
            strength = gr.Slider(0.0, MAX_STRENGTH, value=DEFAULT_STRENGTH, step=0.25, label="Guidance strength",
                                 info="higher meets the targets more closely, at some cost in naturalness",
                                 elem_id="control-strength")
            with gr.Accordion("Sampling", open=False):
                seed = gr.Number(value=0, precision=0, minimum=0, maximum=MAX_SEED, label="Seed")
                sampler_radio = gr.Radio(choices, value=sampler, label="Sampler", visible=with_student,
                                         elem_id="control-sampler")
                steps = steps_slider(sampler, "Diffusion steps" if with_student else "Diffusion steps (DDIM)",
                                     elem_id="control-steps")
                cfg = gr.Slider(0.0, MAX_CFG, value=DEFAULT_CFG, step=0.5, label="Guidance (CFG scale)")
                foot_lock = foot_lock_checkbox("control-foot-lock")
            button = gr.Button("Generate with control", variant="primary", elem_id="control-button")
            preview = gr.Plot(initial_preview(seconds.value, speed.value), label="The targets, from above",
                              elem_id="control-preview")
        with gr.Column(scale=3, min_width=RESULTS_MIN_WIDTH):
            gr.Markdown("**Guided motion**: targets in green, the target path on the floor",
                        elem_classes="video-caption")
            video = gr.Video(label="Guided motion", show_label=False, autoplay=True, loop=True, interactive=False,
                             elem_id="control-video")
            top_view = gr.Plot(label="Target and achieved pelvis path, from above", elem_id="control-top-view")
            summary = gr.Markdown(elem_id="control-summary")
            bvh_units = bvh_units_dropdown("control-bvh-units")
            downloads = gr.File(label="Downloads: MP4, BVH, NPY joints and features, NPZ, control signal (NPZ)",
                                file_count="multiple", interactive=False, elem_id="control-downloads")
    return ControlPanel(prompt, task, path_group, preset, seconds, speed, upload_group, upload, example, upload_help,
                        keyframes, strength, seed, steps, cfg, foot_lock, sampler_radio, button, preview, video,
                        top_view, summary, downloads, bvh_units)
