"""`python -m app.bench`: the studio's latency as a user meets it, measured through its API.

It serves the studio on a free local port with the given model and, with gradio_client, times
each request from the call to the finished response (the video file is written and its path
returned, so the page can show it): generations at the default settings, then edits of the
first prompt (the first edit of a source, and a second edit of the same source, which
reuses the rendered source panel). The targets are 3 s to the first video and 5 s from an edit
to its side-by-side video; the table says which are met. Run it on a quiet machine.
"""
from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

from salad.files import atomic_write_text

GENERATE_TARGET_S, EDIT_TARGET_S = 3.0, 5.0
PROMPTS = ("a person waves their right hand", "a person walks forward and turns left",
           "an exhausted person walks forward")
# (mode, target prompt, mirrored part); the second set edits the same sources (same seeds) again
EDITS = (("swap", "a person waves their left hand", "none"), ("mirror", "", "all"))
EDITS_AGAIN = (("swap", "a person raises their right hand", "none"), ("mirror", "", "upper"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _timed(call) -> float:
    t = time.perf_counter()
    call()
    return time.perf_counter() - t


def remove_download_leftovers(since: float) -> int:
    """gradio_client downloads each file through a fresh `<tmp>/<40 hex>` folder and moves the
    file on, leaving the folder behind; remove the empty ones made since `since` (time.time())."""
    removed = 0
    for d in Path(tempfile.gettempdir()).iterdir():
        try:
            if (len(d.name) == 40 and all(c in "0123456789abcdef" for c in d.name) and d.is_dir()
                    and d.stat().st_mtime >= since - 1 and not any(d.iterdir())):
                d.rmdir()
                removed += 1
        except OSError:          # gone already, or filled meanwhile: not ours to touch
            pass
    return removed


CFG = 7.5


def run(model: str | None, steps: int | None, sampler: str, bf16: bool, threads: int | None) -> dict:
    """steps=None: the sampler's default (salad.pipeline.DEFAULT_STEPS: 50 for ddim and dpm, 4 for
    the consistency student)."""
    from gradio_client import Client

    from .server import create_app, launch
    from .settings import Settings

    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(model=model, port=_free_port(), tmp_dir=Path(tmp), bf16=bf16, threads=threads)
        studio_app = create_app(settings)
        if studio_app.studio is None:
            raise SystemExit(f"the studio could not load a model: {studio_app.error}")
        try:
            # the pipeline's own check: the default steps, and a clear refusal of a student the model lacks
            steps, _, sampler, _ = studio_app.studio.pipe.check_sampling(steps, CFG, sampler)
        except ValueError as exc:
            studio_app.close()
            raise SystemExit(f"cannot benchmark the {sampler} sampler: {exc}") from None
        try:
            client = Client(launch(studio_app, settings, block=False), verbose=False, download_files=tmp)

            def generate(prompt: str, seed: int):
                return client.predict(prompt, True, 4.0, seed, steps, CFG, sampler, api_name="/generate")

            def edit(mode: str, target: str, mirror: str, seed: int):
                return client.predict(PROMPTS[0], mode, target, None, "", 2.0, mirror, 0.2, True, 4.0, seed, steps,
                                      CFG, sampler, api_name="/edit")

            generate("a person walks", 99)          # warm-up: text encoder, kernels, renderer
            gen = [_timed(lambda p=p: generate(p, 0)) for p in PROMPTS]
            first = [_timed(lambda e=e, i=i: edit(*e, 10 + i)) for i, e in enumerate(EDITS)]
            again = [_timed(lambda e=e, i=i: edit(*e, 10 + i)) for i, e in enumerate(EDITS_AGAIN)]
        finally:
            studio_app.close()
            remove_download_leftovers(started)
    return {"settings": {"model": model or "embedded", "steps": steps, "sampler": sampler, "bf16": bf16,
                         "threads": threads},
            "generate_s": gen, "edit_first_s": first, "edit_same_source_s": again,
            "targets_s": {"generate": GENERATE_TARGET_S, "edit": EDIT_TARGET_S}}


def format_table(report: dict) -> str:
    rows = [("generate → video", report["generate_s"], GENERATE_TARGET_S),
            ("edit → side-by-side (new seed)", report["edit_first_s"], EDIT_TARGET_S),
            ("edit again, same source", report["edit_same_source_s"], EDIT_TARGET_S)]
    s = report["settings"]
    lines = [f"studio latency, {s['model']} model, {s['sampler']}-{s['steps']}, "
             f"{'bf16' if s['bf16'] else 'fp32'}, threads {s['threads'] or 'default'}", "",
             f"{'request':32s} {'median s':>9s} {'max s':>7s} {'target s':>9s}  met"]
    for name, times, target in rows:
        med = statistics.median(times)
        lines.append(f"{name:32s} {med:9.2f} {max(times):7.2f} {target:9.1f}  {'yes' if med <= target else 'NO'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m app.bench", description=__doc__.splitlines()[0])
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--steps", type=int, default=None,
                   help="sampling steps (default: the sampler's, 50 for ddim and dpm, 4 for consistency)")
    p.add_argument("--sampler", choices=("ddim", "dpm", "consistency"), default="ddim",
                   help="consistency: the model's distilled student")
    p.add_argument("--bf16", action="store_true", help="bf16 autocast (the studio's default is fp32)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--out", type=Path, default=None, help="write the measurements as JSON here")
    a = p.parse_args(argv)
    report = run(a.model, a.steps, a.sampler, a.bf16, a.threads)
    print(format_table(report))
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
