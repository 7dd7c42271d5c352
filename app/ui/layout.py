"""The page: header, one tab per tool, and the wiring of events (each with an api_name)."""
from __future__ import annotations

from pathlib import Path

import gradio as gr

from ..session import Session
from ..settings import Settings
from ..studio import Studio
from .attention_panel import build_attention_panel
from .generate_panel import build_generate_panel
from .handlers import Handlers, escape_md, guard_all

TITLE = "salad motion studio"
CSS = """
#word-chips .wrap { gap: 6px; }
#summary { min-height: 1.5em; }
#motion-video video, #word-video video { object-fit: contain; }
footer { display: none !important; }
"""
THEME = gr.themes.Soft(primary_hue="indigo", secondary_hue="green")
LICENCE_NOTE = ("The embedded model is trained on the Bandai-Namco Research Motion datasets "
                "(CC BY-NC 4.0: attribution, non-commercial use).")

# api_name of every event, for API clients (gradio_client) and the docs.
API_NAMES = ("generate", "attention", "attention_video", "attention_refresh", "length_mode", "load_example")


def _close_session(state) -> None:
    if isinstance(state, Session):
        state.close()


def header_markdown(pipe) -> str:
    encoder = getattr(pipe.text_encoder, "name", type(pipe.text_encoder).__name__)
    model = "/".join(Path(pipe.source).parts[-2:])    # no full server paths on a public page
    return (f"# {TITLE}\n"
            "Text → 3D human motion with skeleton-aware latent diffusion (SALAD), on the CPU. "
            f"Motions up to {pipe.max_seconds:g} s at 20 fps · text encoder {encoder} · model `{model}`")


def build_studio(studio: Studio, settings: Settings) -> gr.Blocks:
    """The full studio over a loaded pipeline."""
    h = guard_all(Handlers(studio))
    ttl = settings.session_ttl_s
    with gr.Blocks(title=TITLE, delete_cache=(int(settings.prune_every_s), int(ttl))) as demo:
        state = gr.State(None, time_to_live=ttl, delete_callback=_close_session)
        gr.Markdown(header_markdown(studio.pipe))
        with gr.Tabs():
            with gr.Tab("Generate", id="generate", elem_id="generate-tab"):
                gen = build_generate_panel(studio.pipe.max_seconds)
            with gr.Tab("Attention", id="attention", elem_id="attention-tab"):
                att = build_attention_panel()
        gr.Markdown(LICENCE_NOTE)

        gen.auto_length.input(h["length_mode"], gen.auto_length, gen.seconds, api_name="length_mode",
                              api_visibility="undocumented", queue=False, show_progress="hidden")
        generated = gr.on(
            [gen.button.click, gen.prompt.submit], h["generate"], inputs=gen.inputs + [state],
            outputs=[state, gen.video, gen.skeleton, gen.summary, gen.downloads, att.word, att.layers,
                     att.first_step, att.last_step, att.heatmap, att.video],
            api_name="generate", preprocess=False, concurrency_id="model", show_progress_on=[gen.video],
            concurrency_limit=settings.concurrency, trigger_mode="once")
        attention_inputs = att.inputs + [state]
        attention_outputs = [att.heatmap, att.overview, att.downloads]
        # After a generation the overview and attention downloads are filled in; picking a word
        # or changing the aggregation updates the views and then the tinted video.
        generated.success(h["attention"], attention_inputs, attention_outputs, api_name="attention_refresh",
                          api_visibility="private", preprocess=False, concurrency_id="views",
                          show_progress="minimal")
        shown = gr.on([att.word.input, att.layers.input, att.first_step.release, att.last_step.release],
                      h["attention"], inputs=attention_inputs, outputs=attention_outputs, api_name="attention",
                      preprocess=False, concurrency_id="views", trigger_mode="always_last")
        shown.success(h["attention_video"], attention_inputs, att.video, api_name="attention_video",
                      preprocess=False, concurrency_id="views", trigger_mode="always_last")
        demo.unload(h["unload"])
    return demo


def build_error_page(message: str) -> gr.Blocks:
    """What the studio shows when it cannot start its model: the reason and how to fix it."""
    with gr.Blocks(title=f"{TITLE}: no model") as demo:
        gr.Markdown(
            f"# {TITLE}\n"
            "## The studio could not load a model\n"
            f"> {escape_md(message)}\n\n"
            "Start it with a trained model directory (holding `vae/` and `denoiser/`):\n\n"
            "```bash\npython -m app --model path/to/model\n# or\nSALAD_MODEL=path/to/model python -m app\n```\n"
            "Train one with `salad train vae` and `salad train denoiser` (see the README).",
            elem_id="startup-error")
    return demo
