"""The Generate tab: prompt and sampling controls, the skeleton viewer and the downloads."""
from __future__ import annotations

from dataclasses import dataclass

import gradio as gr

from salad.diffusion.schedule import CONSISTENCY_GRID
from salad.motion.representation import FPS
from salad.pipeline import DEFAULT_STEPS as SAMPLER_STEPS, MAX_PROMPT_CHARS, MIN_AUTO_FRAMES

from ..examples import EXAMPLE_PROMPTS
from ..settings import DEFAULT_CFG, DEFAULT_SECONDS, MAX_CFG, MAX_SEED, MAX_STEPS, SECONDS_STEP

MIN_SECONDS = MIN_AUTO_FRAMES / FPS    # the pipeline's shortest motion
# Minimum widths (px) at which the controls and the results columns sit side by side: together more
# than an 800 px window offers, so there the results take the full width under the controls.
CONTROLS_MIN_WIDTH = 340
RESULTS_MIN_WIDTH = 380
VIEW_MIN_WIDTH = 300      # the video and the 3D view share a row only when each gets this much
PLOT_CAPTION = "**3D view** · drag to orbit, slide through the frames; the box follows the body"
FOOT_LOCK_LABEL = "Foot lock (pin planted feet)"
FOOT_LOCK_INFO = "planted feet stay put and the legs are re-solved by IK; off shows the decoder's raw joints"


def foot_lock_checkbox(elem_id: str) -> gr.Checkbox:
    """The foot clean-up switch every tab that samples motions has (on, as in the library)."""
    return gr.Checkbox(value=True, label=FOOT_LOCK_LABEL, info=FOOT_LOCK_INFO, elem_id=elem_id)


# The sampler choices: the teacher's SDE-DPM-Solver++ (half DDIM's steps, DDIM-50's fidelity table) as the
# standard, the 50-step DDIM teacher as the quality choice, and with a distilled student the fast student.
FAST_LABEL = f"fast: distilled student, {SAMPLER_STEPS['consistency']} steps"
STANDARD_LABEL = f"standard: SDE-DPM-Solver++, {SAMPLER_STEPS['dpm-sde']} steps"
QUALITY_LABEL = f"quality: DDIM, {SAMPLER_STEPS['ddim']} steps"
DPM_LABEL = "DPM-Solver++"
SAMPLER_LABELS = (("consistency", FAST_LABEL), ("dpm-sde", STANDARD_LABEL), ("ddim", QUALITY_LABEL),
                  ("dpm", DPM_LABEL))
SAMPLER_INFO = {
    "consistency": lambda pipe: (f"fast: the consistency-distilled student (CFG {pipe.guidance_range[0]:g} to "
                                 f"{pipe.guidance_range[1]:g}, at most {CONSISTENCY_GRID} steps; 4 is its best), close "
                                 "to the teacher in a fifteenth of the time (README, Results)"),
    "dpm-sde": lambda pipe: (f"standard: the teacher in {SAMPLER_STEPS['dpm-sde']} steps of SDE-DPM-Solver++, as "
                             "faithful to the real captures as DDIM-50 in half the time"),
    "ddim": lambda pipe: f"quality: the teacher in {SAMPLER_STEPS['ddim']} DDIM steps, the paper's sampler",
    "dpm": lambda pipe: "DPM-Solver++: deterministic, fewer steps for a close result (on the embedded model, 25 steps "
                        "land 7.8 mm from the 250-step DDIM solution, DDIM-20 11 mm, DDIM-50 3.2 mm)",
}


def sampler_choices(samplers) -> list[tuple[str, str]]:
    """(label, sampler) of the offered samplers: the student, the standard, the quality choice, DPM-Solver++."""
    return [(label, s) for s, label in SAMPLER_LABELS if s in samplers]


def sampler_info(pipe, samplers) -> str:
    """What the sampler radio says under its choices."""
    return "; ".join(SAMPLER_INFO[s](pipe) for s, _ in SAMPLER_LABELS if s in samplers)


def guided_sampler(samplers, sampler: str) -> tuple[list[tuple[str, str]], str, bool]:
    """The Control and Real motion tabs' sampler radio (DDIM or the student; no DPM-Solver++):
    (choices, default, shown). Shown only when the model has a student."""
    choices = [(QUALITY_LABEL, "ddim")] + ([(FAST_LABEL, "consistency")] if "consistency" in samplers else [])
    return choices, sampler if sampler == "consistency" and len(choices) > 1 else "ddim", len(choices) > 1


def max_steps(sampler: str) -> int:
    """The steps slider's top for a sampler: the student's grid, or the studio's limit."""
    return CONSISTENCY_GRID if sampler == "consistency" else MAX_STEPS


def steps_slider(sampler: str, label: str = "Diffusion steps", **kwargs) -> gr.Slider:
    """A steps slider at `sampler`'s default (salad.pipeline.DEFAULT_STEPS)."""
    return gr.Slider(1, max_steps(sampler), value=SAMPLER_STEPS[sampler], step=1, label=label, **kwargs)


def steps_for(sampler, **update) -> gr.Slider:
    """The steps slider's update when the sampler changes: its default and range, and `update`
    (unchanged for a value that is not a sampler)."""
    if sampler not in SAMPLER_STEPS:
        return gr.Slider()
    return gr.Slider(value=SAMPLER_STEPS[sampler], maximum=max_steps(sampler), **update)


def bvh_units_dropdown(elem_id: str) -> gr.Dropdown:
    """The length unit of a tab's BVH downloads: centimetres (what Blender, MotionBuilder and most
    BVH readers assume) or metres."""
    return gr.Dropdown([("centimetres (cm)", "cm"), ("metres (m)", "m")], value="cm", label="BVH units",
                       min_width=160, elem_id=elem_id)


@dataclass
class GeneratePanel:
    prompt: gr.Textbox
    auto_length: gr.Checkbox
    seconds: gr.Slider
    seed: gr.Number
    steps: gr.Slider
    cfg: gr.Slider
    sampler: gr.Radio
    foot_lock: gr.Checkbox
    button: gr.Button
    video: gr.Video
    skeleton: gr.Plot
    summary: gr.Markdown
    downloads: gr.File
    bvh_units: gr.Dropdown
    edit_this: gr.Button

    @property
    def inputs(self) -> list:
        # new inputs go last: API clients call the event with positional arguments
        return [self.prompt, self.auto_length, self.seconds, self.seed, self.steps, self.cfg, self.sampler,
                self.foot_lock]


def build_generate_panel(pipe, samplers=("ddim", "dpm"), sampler: str = "ddim") -> GeneratePanel:
    """`samplers`: those offered (app.studio.offered_samplers), `sampler` the default."""
    longest = max(MIN_SECONDS, float(pipe.max_seconds))
    with gr.Row(equal_height=False):
        with gr.Column(scale=2, min_width=CONTROLS_MIN_WIDTH):
            prompt = gr.Textbox(label="Prompt", lines=2, max_lines=4, max_length=MAX_PROMPT_CHARS,
                                placeholder="a person waves their right hand happily", elem_id="prompt")
            gr.Examples(examples=[[p] for p in EXAMPLE_PROMPTS], inputs=[prompt], examples_per_page=8,
                        label="Examples: motions and styles the model was trained on", cache_examples=False,
                        api_name="load_example")
            with gr.Row():
                auto_length = gr.Checkbox(value=True, label="Automatic length", scale=1, min_width=140,
                                          info="the model decides when the motion ends, near what the training data gives such prompts")
                seconds = gr.Slider(MIN_SECONDS, longest, value=min(DEFAULT_SECONDS, longest), step=SECONDS_STEP,
                                    label="Seconds", interactive=False, scale=2, elem_id="seconds")
            with gr.Accordion("Sampling", open=False):
                seed = gr.Number(value=0, precision=0, minimum=0, maximum=MAX_SEED, label="Seed", elem_id="seed")
                sampler_radio = gr.Radio(sampler_choices(samplers), value=sampler, label="Sampler",
                                         info=sampler_info(pipe, samplers), elem_id="sampler")
                steps = steps_slider(sampler, elem_id="steps")
                cfg = gr.Slider(0.0, MAX_CFG, value=DEFAULT_CFG, step=0.5, label="Guidance (CFG scale)",
                                info="higher follows the text more closely")
                foot_lock = foot_lock_checkbox("foot-lock")
            button = gr.Button("Generate", variant="primary", elem_id="generate-button")
        with gr.Column(scale=3, min_width=RESULTS_MIN_WIDTH):
            with gr.Row(equal_height=False):
                # Captions above the views instead of label badges, which would cover the video's
                # burned-in title and the plot's legend.
                with gr.Column(min_width=VIEW_MIN_WIDTH):
                    gr.Markdown("**Skeleton video**", elem_classes="video-caption")
                    video = gr.Video(label="Skeleton video", show_label=False, autoplay=True, loop=True,
                                     interactive=False, elem_id="motion-video")
                with gr.Column(min_width=VIEW_MIN_WIDTH):
                    gr.Markdown(PLOT_CAPTION, elem_classes="video-caption", elem_id="skeleton-caption")
                    skeleton = gr.Plot(label="3D view", show_label=False, elem_id="skeleton-plot")
            summary = gr.Markdown(elem_id="summary")
            # the Edit tab takes this motion's prompt, seed and sampling, so its edits start from this very motion
            edit_this = gr.Button("Edit this motion", size="sm", elem_id="edit-this-button")
            bvh_units = bvh_units_dropdown("bvh-units")
            downloads = gr.File(label="Downloads: MP4 video, BVH, NPY joints, NPY features, "
                                      "NPZ joints + features",
                                file_count="multiple", interactive=False, elem_id="downloads")
    return GeneratePanel(prompt, auto_length, seconds, seed, steps, cfg, sampler_radio, foot_lock, button, video,
                         skeleton, summary, downloads, bvh_units, edit_this)
