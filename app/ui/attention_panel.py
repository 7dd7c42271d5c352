"""The Attention tab: which body parts each word of the prompt steered, over time."""
from __future__ import annotations

from dataclasses import dataclass

import gradio as gr

from ..settings import DEFAULT_STEPS

INTRO = (
    "Cross-attention of the denoiser between the prompt's words and the 7 body parts, frame by frame, "
    "captured while the motion was sampled. Pick a word to see its map and the skeleton tinted by it; "
    "choose which layers and which sampling steps to average.")
# Measured on the shipped model (right/left wave and raise prompts, 2 seeds, maps averaged over
# layers, steps and frames): what the maps mean is the network's own routing, not the labels'.
READING_NOTE = (
    "**Reading side words.** The action verb attends most to the arm that acts (for a right-hand wave, 0.23 of "
    "the verb's attention goes to the right upper body against 0.12 to the left), but *left* and *right* attend "
    "most to the **other** arm (0.18-0.23), and *hand* least to the acting one. The part labels are right (the "
    "verb's map shows it): this model uses the side word to mark which arm stays down, so read a side word's "
    "map as where the action is *not*.")


@dataclass
class AttentionPanel:
    word: gr.Radio
    layers: gr.CheckboxGroup
    first_step: gr.Slider
    last_step: gr.Slider
    heatmap: gr.Plot
    video: gr.Video
    overview: gr.Plot
    downloads: gr.File

    @property
    def inputs(self) -> list:
        return [self.word, self.layers, self.first_step, self.last_step]


def build_attention_panel() -> AttentionPanel:
    gr.Markdown(INTRO)
    word = gr.Radio([], label="Word (generate a motion first)", elem_id="word-chips")
    with gr.Row():
        layers = gr.CheckboxGroup([], label="Layers", scale=2, min_width=200)
        first_step = gr.Slider(1, DEFAULT_STEPS, value=1, step=1, label="First step (1 = noisiest)", scale=1)
        last_step = gr.Slider(1, DEFAULT_STEPS, value=DEFAULT_STEPS, step=1, label="Last step", scale=1)
    with gr.Row(equal_height=True):
        heatmap = gr.Plot(label="The word's attention over body parts and time", elem_id="word-heatmap")
        with gr.Column():
            # a caption, not a label badge: the badge would cover the video's burned-in title
            gr.Markdown("**Joints tinted by the word's attention**", elem_classes="video-caption")
            video = gr.Video(label="Joints tinted by the word's attention", show_label=False, autoplay=True,
                             loop=True, interactive=False, elem_id="word-video")
    gr.Markdown(READING_NOTE, elem_id="attention-reading-note")
    overview = gr.Plot(label="All words on one colour scale", elem_id="attention-overview")
    downloads = gr.File(label="Attention maps: NPZ (this aggregation + raw per step and layer) and PNG",
                        file_count="multiple", interactive=False, elem_id="attention-downloads")
    return AttentionPanel(word, layers, first_step, last_step, heatmap, video, overview, downloads)
