"""The Edit tab: one control per attention-modulation strategy (word swap, refinement,
re-weighting, mirroring), the side-by-side result and both attention maps of a word."""
from __future__ import annotations

from dataclasses import dataclass

import gradio as gr

from salad.models.text import split_words
from salad.pipeline import MAX_PROMPT_CHARS

from ..settings import (
    DEFAULT_CFG, DEFAULT_REWEIGHT, DEFAULT_SECONDS, DEFAULT_SELF_INJECT, DEFAULT_TAU, MAX_CFG, MAX_REWEIGHT, MAX_SEED,
    SECONDS_STEP,
)
from .generate_panel import (
    CONTROLS_MIN_WIDTH, MIN_SECONDS, RESULTS_MIN_WIDTH, bvh_units_dropdown, foot_lock_checkbox, sampler_choices,
    sampler_info, steps_slider,
)

INTRO = ("Edit a motion without retraining: the source prompt and the edit are sampled together from the same "
         "noise, and the edit changes only the cross-attention between words and body parts.")
FILES_NOTE = "The edited motion's own MP4 and the attention maps join the downloads after each edit."
MODES = [("word swap", "swap"), ("refine (add words)", "refine"), ("re-weight a word", "reweight"),
         ("mirror left/right", "mirror")]
MODE_HELP = {
    "swap": "Replace words, keeping the rest of the motion: the target has as many words as the source.",
    "refine": "Add words (a style, a manner) to the source prompt; the source's maps steer the shared words.",
    "reweight": "Strengthen (s > 1), weaken (0 < s < 1) or invert (s < 0) one word's influence.",
    "mirror": "Swap the attention of left and right limbs: a left-hand wave becomes a right-hand one.",
}
MIRROR_CHOICES = [("no mirroring", "none"), ("legs (lower)", "lower"), ("arms (upper)", "upper"),
                  ("arms and legs (all)", "all")]
HOLD_OPTIONS = [("auto", "auto"), ("lower body", "lower"), ("upper body", "upper"), ("nothing", "none")]
HOLD_INFO = ("the held body half moves as in the source while the edit changes the rest (lower: the legs and the "
             "path); auto keeps the legs and the path of a standing action when re-weighting a word")
EXAMPLE_EDITS = [
    ["a person waves their right hand happily", "swap", "a person waves their left hand happily"],
    ["a person walks forward", "refine", "an exhausted person walks forward slowly"],
    ["a person waves their left hand", "mirror", ""],
    ["a person raises both hands proudly", "reweight", ""],
]


@dataclass
class EditPanel:
    source: gr.Textbox
    mode: gr.Radio
    mode_help: gr.Markdown
    target: gr.Textbox
    tau: gr.Slider
    reweight_word: gr.Dropdown
    reweight_scale: gr.Slider
    mirror: gr.Radio
    self_inject: gr.Slider
    hold: gr.Dropdown
    auto_length: gr.Checkbox
    seconds: gr.Slider
    seed: gr.Number
    steps: gr.Slider
    cfg: gr.Slider
    sampler: gr.Radio
    foot_lock: gr.Checkbox
    button: gr.Button
    video: gr.Video
    summary: gr.Markdown
    word: gr.Radio
    source_heatmap: gr.Plot
    edited_heatmap: gr.Plot
    downloads: gr.File
    bvh_units: gr.Dropdown
    files_status: gr.Markdown

    @property
    def inputs(self) -> list:
        return [self.source, self.mode, self.target, self.tau, self.reweight_word, self.reweight_scale, self.mirror,
                self.self_inject, self.hold, self.auto_length, self.seconds, self.seed, self.steps, self.cfg,
                self.sampler, self.foot_lock]


def build_edit_panel(pipe, samplers=("ddim", "dpm"), sampler: str = "ddim") -> EditPanel:
    """`samplers`: those offered (app.studio.offered_samplers), `sampler` the default."""
    longest = max(MIN_SECONDS, float(pipe.max_seconds))
    gr.Markdown(INTRO)
    with gr.Row(equal_height=False):
        with gr.Column(scale=2, min_width=CONTROLS_MIN_WIDTH):
            source = gr.Textbox(label="Source prompt", lines=2, max_lines=4, max_length=MAX_PROMPT_CHARS,
                                value=EXAMPLE_EDITS[0][0], elem_id="edit-source")
            mode = gr.Radio(MODES, value="swap", label="Edit", elem_id="edit-mode")
            mode_help = gr.Markdown(MODE_HELP["swap"], elem_id="edit-mode-help")
            target = gr.Textbox(label="Target prompt (the source with words replaced)", lines=2, max_lines=4,
                                max_length=MAX_PROMPT_CHARS, value=EXAMPLE_EDITS[0][2],
                                elem_id="edit-target")
            tau = gr.Slider(0.0, 1.0, value=DEFAULT_TAU["swap"], step=0.05, elem_id="edit-tau",
                            label="τ: the source's attention leads while the timestep t ≥ τ·T",
                            info="0.8: the first 20% of the steps follow the source; 0: all of them")
            with gr.Row():
                first_words = [("none", "")] + [(w, w) for w in dict.fromkeys(split_words(EXAMPLE_EDITS[0][2]))]
                reweight_word = gr.Dropdown(first_words, value="", label="Word to re-weight", scale=1, min_width=140,
                                            elem_id="edit-reweight-word",
                                            info="a word of the prompt being edited; optional with swap/refine")
                reweight_scale = gr.Slider(-MAX_REWEIGHT, MAX_REWEIGHT, value=DEFAULT_REWEIGHT, step=0.1, scale=2,
                                           label="s: its attention scale", elem_id="edit-reweight-scale",
                                           info="1 = unchanged, 0 = ignored, < 0 = inverted")
            mirror = gr.Radio(MIRROR_CHOICES, value="none", label="Mirror (also with any other edit)",
                              elem_id="edit-mirror")
            self_inject = gr.Slider(0.0, 1.0, value=DEFAULT_SELF_INJECT, step=0.05, elem_id="edit-self-inject",
                                    label="Self-attention injection: share of the first steps that reuse the "
                                          "source's self-attention", info="higher keeps the timing and pose closer")
            hold = gr.Dropdown(HOLD_OPTIONS, value="auto", label="Hold to the source", info=HOLD_INFO,
                               elem_id="edit-hold")
            with gr.Accordion("Sampling", open=False):
                with gr.Row():
                    auto_length = gr.Checkbox(value=True, label="Automatic length", scale=1, min_width=140)
                    seconds = gr.Slider(MIN_SECONDS, longest, value=min(DEFAULT_SECONDS, longest), step=SECONDS_STEP,
                                        label="Seconds", interactive=False, scale=2, elem_id="edit-seconds")
                seed = gr.Number(value=0, precision=0, minimum=0, maximum=MAX_SEED, label="Seed", elem_id="edit-seed")
                sampler_radio = gr.Radio(sampler_choices(samplers), value=sampler, label="Sampler",
                                         info=sampler_info(pipe, samplers), elem_id="edit-sampler")
                steps = steps_slider(sampler, elem_id="edit-steps")
                cfg = gr.Slider(0.0, MAX_CFG, value=DEFAULT_CFG, step=0.5, label="Guidance (CFG scale)")
                foot_lock = foot_lock_checkbox("edit-foot-lock")
            button = gr.Button("Edit", variant="primary", elem_id="edit-button")
            gr.Examples(examples=EXAMPLE_EDITS, inputs=[source, mode, target], label="Example edits",
                        cache_examples=False, api_name="load_edit_example")
        with gr.Column(scale=3, min_width=RESULTS_MIN_WIDTH):
            # The panels carry their own "source" / "edited" captions, which a label badge would cover.
            gr.Markdown("**Source and edited, in sync**", elem_classes="video-caption")
            video = gr.Video(label="Source and edited, in sync", show_label=False, autoplay=True, loop=True,
                             interactive=False, elem_id="edit-video")
            summary = gr.Markdown(elem_id="edit-summary")
            word = gr.Radio([], label="Word (run an edit first): its attention before and after",
                            elem_id="edit-word")
            with gr.Row(equal_height=True):
                source_heatmap = gr.Plot(label="Source", elem_id="edit-source-heatmap")
                edited_heatmap = gr.Plot(label="Edited", elem_id="edit-edited-heatmap")
            bvh_units = bvh_units_dropdown("edit-bvh-units")
            # The remaining downloads' rendering shows its progress on this line: on the file list itself
            # the progress bar covered the files.
            files_status = gr.Markdown(FILES_NOTE, elem_id="edit-files-status", elem_classes="files-status")
            downloads = gr.File(label="Downloads: side-by-side and edited MP4, BVH, NPY joints and features, NPZ, "
                                      "attention maps (NPZ, PNG)", file_count="multiple", interactive=False,
                                elem_id="edit-downloads")
    return EditPanel(source, mode, mode_help, target, tau, reweight_word, reweight_scale, mirror, self_inject,
                     hold, auto_length, seconds, seed, steps, cfg, sampler_radio, foot_lock, button, video, summary,
                     word, source_heatmap, edited_heatmap, downloads, bvh_units, files_status)
