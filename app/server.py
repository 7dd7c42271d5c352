"""Assemble and serve the studio: workspace, pipeline (or an error page), Gradio queue and server."""
from __future__ import annotations

import logging
import os
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

from .settings import Settings
from .workspace import Workspace

log = logging.getLogger("salad.studio")
MAX_UPLOAD = "4mb"     # control targets and motions (BVH, NPY); app.settings.MAX_UPLOAD_BYTES is checked again


@dataclass
class StudioApp:
    demo: "object"               # gr.Blocks
    workspace: Workspace
    studio: "object | None"      # Studio, or None when no model could be loaded
    error: str | None = None
    closed: bool = False

    def close(self) -> None:
        try:
            self.demo.close()
        finally:
            self.closed = True
            if self.studio is not None:
                from salad.render import stop_workers

                stop_workers()
                self.studio.close()
            self.workspace.close()


def _warm_up(app: StudioApp, render_workers: int) -> None:
    from salad.render import start_workers, stop_workers, warm_up

    try:
        backend = warm_up()
        # after the warm-up, which settles the GL platform the workers inherit
        start_workers(render_workers)
        if app.closed:          # closed meanwhile: no worker outlives its studio
            stop_workers()
            return
        log.info("renderer ready (%s, %d render worker(s))", backend, render_workers)
    except Exception:       # renders will then report the problem per request
        log.exception("renderer warm-up failed")


def _load(settings: Settings):
    from salad.pipeline import load_pipeline

    try:
        # the CPU, as before the pipeline took a device: the studio has not been tried on a GPU
        bf16, min_rows = settings.bf16_rows
        return load_pipeline(settings.model, bf16=bf16, bf16_min_rows=min_rows, threads=settings.threads,
                             device="cpu"), None
    except Exception as exc:     # any failure to load becomes the error page, not a crash
        log.error("no model: %s", exc)
        return None, f"{type(exc).__name__}: {exc}"


def _gradio_cache_key(path: Path) -> str:
    """The folder name Gradio gives the cached copy of a file it serves (gradio.processing_utils.save_file_to_cache)."""
    from gradio.processing_utils import hash_file

    return hash_file(path)


def create_app(settings: Settings, pipe=None) -> StudioApp:
    """Build the studio (or, without a loadable model, the error page) around a fresh workspace.
    `pipe` skips loading when a pipeline is already at hand."""
    workspace = Workspace(settings.tmp_dir, ttl_s=settings.session_ttl_s, cache_key=_gradio_cache_key)
    # Gradio copies every file it serves into its cache; keep that cache inside our root.
    os.environ["GRADIO_TEMP_DIR"] = str(workspace.gradio_cache)
    from .model_thread import ModelThread

    model_thread = ModelThread()
    try:
        from .studio import Studio
        from .ui.layout import build_error_page, build_studio

        error, loaded_here = None, pipe is None
        if loaded_here:
            pipe, error = model_thread.run(_load, settings)
        if pipe is None:
            model_thread.close()
            return StudioApp(build_error_page(error), workspace, None, error)
        if loaded_here:
            # a pipeline loaded by another thread has its team there already; the caller keeps its threads
            model_thread.own_torch()
        studio = Studio(pipe, workspace, settings.control_examples, sampler=settings.sampler,
                        model_thread=model_thread)
        demo = build_studio(studio, settings)
        demo.queue(default_concurrency_limit=settings.concurrency, max_size=settings.queue_size)
        return StudioApp(demo, workspace, studio)
    except BaseException:
        model_thread.close()
        workspace.close()
        raise


def _outside(path: Path, parent: str) -> bool:
    try:
        path.relative_to(Path(parent).resolve())
        return False
    except ValueError:
        return True


def launch(app: StudioApp, settings: Settings, block: bool = True) -> str:
    """Serve `app` on settings.host:port (no share link); returns the local URL. With
    block=False the server runs in background threads until app.close()."""
    from .ui.layout import CSS, THEME
    from .ui.notes import NOTES_JS

    if app.studio is not None:
        app.workspace.start_janitor(settings.prune_every_s)
        threading.Thread(target=_warm_up, args=(app, settings.render_workers), name="render-warm-up",
                         daemon=True).start()
    # Returned files must lie under the temp dir or the working directory to be served,
    # unless allowed; allow exactly the sessions folder when it lies elsewhere.
    root = app.workspace.sessions
    allowed = [str(root)] if _outside(root, tempfile.gettempdir()) and _outside(root, os.getcwd()) else None
    # show_error: a refusal Gradio makes itself (too few inputs, a value its component cannot read) reaches
    # API clients as its message rather than {"error": null}; the handlers' own errors always did, and their
    # internal failures are already reduced to a generic message (app.ui.handlers.guarded).
    _, url, _ = app.demo.launch(
        server_name=settings.host, server_port=settings.port, share=False, prevent_thread_lock=not block,
        show_error=True, allowed_paths=allowed, max_file_size=MAX_UPLOAD, ssr_mode=False, pwa=False,
        mcp_server=False, enable_monitoring=False, quiet=True, theme=THEME, css=CSS,
        footer_links=["api"], state_session_capacity=1000, js=NOTES_JS)
    return url
