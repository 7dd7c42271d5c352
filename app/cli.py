"""`python -m app`: start the studio."""
from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from .settings import DEFAULT_SAMPLER, PRECISIONS, STUDIO_SAMPLERS, Settings, default_clips, default_host, default_port


def parse_args(argv: list[str] | None = None) -> Settings:
    p = argparse.ArgumentParser(prog="python -m app", description="The salad motion studio (Gradio).")
    p.add_argument("--model", metavar="DIR", default=None,
                   help="model directory with vae/ and denoiser/ (default: $SALAD_MODEL, else assets/model)")
    p.add_argument("--host", default=default_host(),
                   help="address to bind (default 127.0.0.1, or $GRADIO_SERVER_NAME); 0.0.0.0 exposes the studio")
    p.add_argument("--port", type=int, default=default_port(), help="port (default 7860, or $GRADIO_SERVER_PORT)")
    p.add_argument("--concurrency", type=int, default=2, help="jobs served at once (default 2; sampling is serialised)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--precision", choices=PRECISIONS, default="auto",
                   help="auto (default): bf16 autocast for forwards of 2 rows or more (guided steps, edits) on a "
                        "CPU with native bf16, fp32 for single rows and elsewhere; fp32 or bf16: every forward")
    p.add_argument("--render-workers", type=int, default=1, metavar="N",
                   help="helper processes that draw a share of every video's frames beside the server (default 1; "
                        "0 draws in the server alone)")
    p.add_argument("--tmp-dir", type=Path, default=None, help="where the studio's temp folder goes (default: $TMPDIR)")
    p.add_argument("--session-ttl", type=float, default=7200.0,
                   help="seconds after which an idle session and its files are removed (default 7200)")
    p.add_argument("--control-examples", type=Path, default=None, metavar="DIR",
                   help="a folder of control .npy files (MoLA's format) to offer in the Control tab")
    p.add_argument("--clips", type=Path, default=None, metavar="DIR",
                   help="a dataset build (HumanML3D layout, from `salad data build`) whose test clips the Real "
                        "motion tab offers (default: data/bandai-hml when it has been built)")
    p.add_argument("--no-clips", action="store_true", help="offer no test clips in the Real motion tab")
    p.add_argument("--sampler", choices=STUDIO_SAMPLERS, default=DEFAULT_SAMPLER,
                   help="the panels' default sampler (default auto: the teacher in 25 steps of dpm-sde, and for "
                        "guided control the distilled student, 4 steps, when the model has one, else DDIM-50); "
                        "consistency asks for the student everywhere; ddim for the 50-step teacher")
    a = p.parse_args(argv)
    if a.no_clips and a.clips is not None:
        p.error("--clips and --no-clips exclude each other")
    clips = None if a.no_clips else (a.clips if a.clips is not None else default_clips())
    try:
        return Settings(model=a.model, host=a.host, port=a.port, concurrency=a.concurrency, threads=a.threads,
                        precision=a.precision, tmp_dir=a.tmp_dir, session_ttl_s=a.session_ttl,
                        control_examples=a.control_examples, clips=clips, sampler=a.sampler,
                        render_workers=a.render_workers)
    except ValueError as exc:
        p.error(str(exc))


def _stop(signum, frame):
    # Let Gradio shut down as on Ctrl-C, so the workspace is removed on the way out.
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = parse_args(argv)
    from .server import create_app, launch

    app = create_app(settings)
    signal.signal(signal.SIGTERM, _stop)
    try:
        print(f"salad studio on http://{settings.host}:{settings.port}", file=sys.stderr, flush=True)
        launch(app, settings, block=True)
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
    return 0
