"""The page: header, one tab per tool, and the wiring of events (each with an api_name)."""
from __future__ import annotations

import logging
from pathlib import Path

import gradio as gr

from ..session import Session
from ..settings import Settings
from ..studio import Studio
from ..controls import list_examples
from ..real_input import ClipLibrary
from .attention_panel import build_attention_panel
from .control_panel import build_control_panel
from .edit_panel import build_edit_panel
from .generate_panel import build_generate_panel
from .handlers import Handlers, guard_all
from .real_panel import build_real_panel
from .summaries import escape_md

log = logging.getLogger("salad.studio")
TITLE = "salad motion studio"
CSS = """
#word-chips .wrap { gap: 6px; }
#summary, #edit-summary, #control-summary, #real-summary { min-height: 1.5em; }
#motion-video video, #word-video video, #edit-video video, #control-video video, #real-video video {
  object-fit: contain; }
/* Captions take their own line height: as flex items with overflow:auto they were squeezed and clipped. */
div.block.video-caption { flex: none; overflow: visible !important; margin-bottom: -4px; }
.files-status { flex: none; min-height: 2.6em; }
/* A long download name loses its start rather than its end, which tells _joints.npy from _features.npy. */
.file-preview .filename .stem { direction: rtl; text-align: left; }
footer { display: none !important; }
.salad-note { margin-top: 4px; padding: 4px 8px; border-radius: 6px; background: #fff4d6; color: #6b4b00;
  font-size: 0.85rem; line-height: 1.35; }
"""
THEME = gr.themes.Soft(primary_hue="indigo", secondary_hue="green")
LICENCE_NOTE = ("The embedded model is trained on the Bandai-Namco Research Motion datasets "
                "(CC BY-NC 4.0: attribution, non-commercial use).")

# api_name of every event, for API clients (gradio_client) and the docs.
API_NAMES = ("generate", "generate_video", "attention", "attention_video", "attention_refresh", "length_mode",
             "load_example", "edit", "edit_video", "edit_files", "edit_attention", "edit_mode", "edit_words",
             "edit_length_mode", "load_edit_example",
             "control", "control_video", "control_task", "control_preview", "control_preview_refresh",
             "edit_real", "real_mode", "real_words", "real_clip", "real_upload",
             "sampler_steps", "edit_sampler_steps", "control_sampler_steps", "real_sampler",
             "bvh_units", "edit_bvh_units", "control_bvh_units", "real_bvh_units")


def _full_video(h: dict, kind: str, api_name: str, panel, made, state, refreshed: tuple = ()):
    """After `made` (a result shown with its preview video): the antialiased MP4 replaces the
    preview and joins the downloads, and the `refreshed` views show the motion as refined. Renders
    queue apart from the views ("render"), so that a word click or a relisting never waits for one;
    the render lock serialises them anyway."""
    return made.success(h[api_name], [panel.bvh_units, state], [panel.video, panel.downloads, *refreshed],
                        api_name=api_name,
                        preprocess=False, concurrency_id="render", concurrency_limit=1, show_progress="minimal",
                        show_progress_on=[panel.video])


def _close_session(state) -> None:
    if isinstance(state, Session):
        state.close()


def header_markdown(pipe) -> str:
    encoder = getattr(pipe.text_encoder, "name", type(pipe.text_encoder).__name__)
    model = "/".join(Path(pipe.source).parts[-2:])    # no full server paths on a public page
    return (f"# {TITLE}\n"
            "Text → 3D human motion with skeleton-aware latent diffusion (SALAD), on the CPU. "
            f"Motions up to {pipe.max_seconds:g} s at 20 fps · text encoder {encoder} · model `{model}`")


def _clip_library(settings: Settings) -> ClipLibrary | None:
    """The test clips of settings.clips, or None (and the tab says how to get some) when there are
    none or the build cannot be read: a broken dataset must not keep the studio from starting."""
    if settings.clips is None:
        return None
    try:
        clips = ClipLibrary(settings.clips)
    except (OSError, ValueError) as exc:
        log.error("no test clips offered: %s", exc)
        return None
    log.info("%d test clips offered from %s", len(clips), settings.clips)
    return clips if len(clips) else None


def build_studio(studio: Studio, settings: Settings) -> gr.Blocks:
    """The full studio over a loaded pipeline."""
    clips = _clip_library(settings)
    h = guard_all(Handlers(studio, clips))
    ttl = settings.session_ttl_s
    pipe, samplers, sampler = studio.pipe, studio.samplers, studio.default_sampler
    with gr.Blocks(title=TITLE, delete_cache=(int(settings.prune_every_s), int(ttl))) as demo:
        state = gr.State(None, time_to_live=ttl, delete_callback=_close_session)
        gr.Markdown(header_markdown(studio.pipe))
        with gr.Tabs() as tabs:
            with gr.Tab("Generate", id="generate", elem_id="generate-tab"):
                gen = build_generate_panel(pipe, samplers, sampler)
            with gr.Tab("Attention", id="attention", elem_id="attention-tab"):
                att = build_attention_panel()
            with gr.Tab("Edit", id="edit", elem_id="edit-tab"):
                ed = build_edit_panel(pipe, samplers, studio.edit_sampler)
            with gr.Tab("Control", id="control", elem_id="control-tab"):
                ctl = build_control_panel(pipe, list_examples(studio.control_examples), samplers,
                                          studio.control_sampler)
            with gr.Tab("Real motion", id="real", elem_id="real-tab"):
                real = build_real_panel(clips.choices() if clips else [], samplers, studio.edit_sampler)
        gr.Markdown(LICENCE_NOTE)

        gen.auto_length.input(h["length_mode"], gen.auto_length, gen.seconds, api_name="length_mode",
                              api_visibility="undocumented", queue=False, show_progress="hidden")
        # a new sampler starts at its own default steps (4 for the student, 50 for the teacher)
        gen.sampler.change(h["sampler_steps"], gen.sampler, gen.steps, api_name="sampler_steps", preprocess=False,
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
        # the tinted video renders apart from the views: the next word's map need not wait for it
        shown.success(h["attention_video"], attention_inputs, att.video, api_name="attention_video",
                      preprocess=False, concurrency_id="render", concurrency_limit=1, trigger_mode="always_last")
        # the preview first (with everything else), then the antialiased MP4 (the download)
        rendered = _full_video(h, "generate", "generate_video", gen, generated, state, (gen.skeleton, gen.summary))
        _wire_units(h, "generate", "bvh_units", gen, rendered, state)
        _wire_edit(h, ed, state, settings)
        gen.edit_this.click(h["edit_generated"], [state],
                            [tabs, ed.source, ed.target, ed.auto_length, ed.seconds, ed.seed, ed.steps, ed.cfg,
                             ed.sampler, ed.foot_lock], api_name="edit_generated", preprocess=False, queue=False)
        _wire_control(h, ctl, generated, state, settings)
        _wire_real(h, real, state, settings)
        demo.unload(h["unload"])
    return demo


def _wire_units(h: dict, kind: str, api_name: str, panel, made, state) -> None:
    """A tab's BVH units: choosing them relists its downloads, and so does the last step of every
    new result (`made`), whose BVH files are saved in centimetres."""
    handler = h[f"bvh_units_{kind}"]
    panel.bvh_units.input(handler, [panel.bvh_units, state], panel.downloads, api_name=api_name, preprocess=False,
                          concurrency_id="views", show_progress="hidden")
    made.success(handler, [panel.bvh_units, state], panel.downloads, api_name=f"{api_name}_refresh",
                 api_visibility="private", preprocess=False, concurrency_id="views", show_progress="hidden")


def _wire_edit(h: dict, ed, state, settings: Settings) -> None:
    """The Edit tab: controls follow the mode; an edit shows its preview video and maps first, then
    its antialiased video, then its remaining downloads (the edited motion's own MP4, attention
    NPZ/PNG) are made."""
    quick = dict(queue=False, show_progress="hidden", api_visibility="undocumented")
    ed.mode.change(h["edit_mode"], [ed.mode, ed.mirror, ed.source, ed.target, ed.reweight_word],
                   [ed.mode_help, ed.target, ed.tau, ed.mirror, ed.reweight_word], api_name="edit_mode",
                   preprocess=False, **quick)
    gr.on([ed.source.change, ed.target.change], h["edit_words"],
          [ed.source, ed.mode, ed.target, ed.reweight_word], ed.reweight_word, api_name="edit_words",
          preprocess=False, **quick)
    ed.auto_length.input(h["length_mode"], ed.auto_length, ed.seconds, api_name="edit_length_mode", **quick)
    # the user's choice of sampler only: "Edit this motion" sets the sampler and its steps together
    ed.sampler.input(h["sampler_steps"], ed.sampler, ed.steps, api_name="edit_sampler_steps", preprocess=False,
                     **quick)
    edited = gr.on([ed.button.click], h["edit"], inputs=ed.inputs + [state],
                   outputs=[state, ed.video, ed.summary, ed.word, ed.source_heatmap, ed.edited_heatmap, ed.downloads],
                   api_name="edit", preprocess=False, concurrency_id="model", show_progress_on=[ed.video],
                   concurrency_limit=settings.concurrency, trigger_mode="once")
    rendered = _full_video(h, "edit", "edit_video", ed, edited, state, (ed.summary,))
    files = rendered.success(h["edit_files"], [state], ed.downloads, api_name="edit_files", preprocess=False,
                             concurrency_id="render", concurrency_limit=1, show_progress="minimal",
                             show_progress_on=[ed.files_status])
    _wire_units(h, "edit", "edit_bvh_units", ed, files, state)
    ed.word.input(h["edit_attention"], [ed.word, state], [ed.source_heatmap, ed.edited_heatmap],
                  api_name="edit_attention", preprocess=False, concurrency_id="views", trigger_mode="always_last")


def _wire_control(h: dict, ctl, generated, state, settings: Settings) -> None:
    """The Control tab: inputs follow the kind of targets, a preview of the targets follows
    every change, and a run shows the guided motion with its targets and error (a preview video,
    then the antialiased one)."""
    quick = dict(queue=False, show_progress="hidden", api_visibility="undocumented")
    ctl.task.change(h["control_task"], ctl.task, [ctl.path_group, ctl.upload_group, ctl.upload_help, ctl.keyframes],
                    api_name="control_task", **quick)
    ctl.sampler.change(h["sampler_steps"], ctl.sampler, ctl.steps, api_name="control_sampler_steps",
                       preprocess=False, **quick)
    preview_inputs = [ctl.task, ctl.preset, ctl.seconds, ctl.speed, ctl.upload, ctl.example, ctl.keyframes, state]
    gr.on([ctl.task.change, ctl.preset.change, ctl.seconds.release, ctl.speed.release, ctl.upload.change,
           ctl.example.change, ctl.keyframes.submit, ctl.keyframes.blur],
          h["control_preview"], preview_inputs, ctl.preview, api_name="control_preview", preprocess=False,
          concurrency_id="views", show_progress="hidden", api_visibility="undocumented", trigger_mode="always_last")
    # in-betweening and upper-body targets come from the last generated motion
    generated.success(h["control_preview"], preview_inputs, ctl.preview, api_name="control_preview_refresh",
                      preprocess=False, concurrency_id="views", show_progress="hidden", api_visibility="private")
    guided = gr.on([ctl.button.click], h["control"], inputs=ctl.inputs + [state],
                   outputs=[state, ctl.video, ctl.top_view, ctl.summary, ctl.downloads], api_name="control",
                   preprocess=False, concurrency_id="model", show_progress_on=[ctl.video],
                   concurrency_limit=settings.concurrency, trigger_mode="once")
    rendered = _full_video(h, "control", "control_video", ctl, guided, state, (ctl.top_view, ctl.summary))
    _wire_units(h, "control", "control_bvh_units", ctl, rendered, state)


def _wire_real(h: dict, real, state, settings: Settings) -> None:
    """The Real motion tab: controls follow the mode as in the Edit tab; a picked test clip fills
    in its caption and replaces an upload (and an upload replaces the clip)."""
    quick = dict(queue=False, show_progress="hidden", api_visibility="undocumented")
    real.sampler.change(h["real_sampler"], real.sampler, [real.steps, real.inversion, real.seed],
                        api_name="real_sampler", preprocess=False, **quick)
    real.mode.change(h["real_mode"], [real.mode, real.mirror, real.source, real.target, real.reweight_word],
                     [real.mode_help, real.target, real.mirror, real.reweight_word], api_name="real_mode",
                     preprocess=False, **quick)
    gr.on([real.source.change, real.target.change], h["edit_words"],
          [real.source, real.mode, real.target, real.reweight_word], real.reweight_word, api_name="real_words",
          preprocess=False, **quick)
    # user actions only (.input / .upload): the updates these make must not set each other off
    real.clip.input(h["real_clip"], real.clip, [real.source, real.upload], api_name="real_clip", preprocess=False,
                    **quick)
    # queued: the page shows an error toast for queued events only, and the file is read (checked) here
    real.upload.upload(h["real_upload"], real.upload, real.clip, api_name="real_upload", preprocess=False,
                       concurrency_id="views", show_progress="hidden", api_visibility="undocumented")
    edited = gr.on([real.button.click], h["edit_real"], inputs=real.inputs + [state],
                   outputs=[state, real.video, real.summary, real.downloads], api_name="edit_real",
                   preprocess=False, concurrency_id="model", show_progress_on=[real.video],
                   concurrency_limit=settings.concurrency, trigger_mode="once")
    _wire_units(h, "real", "real_bvh_units", real, edited, state)


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
