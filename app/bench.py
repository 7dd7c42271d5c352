"""`python -m app.bench`: the studio's latency as a user meets it, measured through its API.

It serves the studio on a free local port with the given model and, with gradio_client, times
each request from the call to the finished response and the video it returns fetched, as the page
fetches it to play it (the other files are links the page fetches only when clicked; --fetch-all
downloads every returned file, as gradio_client does by default and as this benchmark did before the
preview came in). The same fixed matmul reference as `salad bench` (50 fp32 1024² matmuls) is measured just
before and just after the timed requests, on the studio's model thread with its torch threads, so that runs
on machines (or hours) of different speed can be compared. A result comes in two steps, as on the page: its main event
("generate", "edit", "control") answers with a preview video (rendered without antialiasing) and
everything else it shows, then the chained "*_video" event renders the antialiased MP4 (the
download) in its place. The rows:

- generate → preview video: generations at the default settings (target 1.5 s);
- generate → full video: the same plus its "generate_video" call (no target);
- edit → preview side-by-side, and → full: edits of the first prompt, the first edit of a source
  (target 2.5 s), then second edits of the same sources, which replay the source's sampling and reuse
  its rendered panel;
- edit this motion → preview side-by-side: the first prompt generated (untimed, with its full video),
  the Edit tab filled from it ("edit_generated"), then the same edits as above timed: the pipeline replays
  the generated motion's sampling, and only the edited branch samples (target 2.5 s);
- control → preview video: a path preset through the "control" API (target 4 s), then → full;
- word click → heatmap: the "attention" API with a word picked after a generation, whose maps are
  kept (nothing is resampled), while the previous word's tinted video renders as it does on the
  page (target 0.5 s).

The samplers are the studio's defaults (app.studio.Studio: the teacher's dpm-sde for text, and for
guided control the distilled student where the model's checkpoint prefers it, else DDIM) unless
--sampler names one (consistency: the model's distilled student, 4 steps; with dpm or dpm-sde the
guided control samples with DDIM, as its tab offers neither). The table says which targets are met.
Run it on a quiet machine.
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

import httpx

from salad.bench import matmul_reference_ms
from salad.files import atomic_write_text

from .settings import PRECISIONS

GENERATE_TARGET_S, EDIT_TARGET_S, CONTROL_TARGET_S, WORD_TARGET_S = 1.5, 2.5, 4.0, 0.5
PROMPTS = ("a person waves their right hand", "a person walks forward and turns left",
           "an exhausted person walks forward")
# (mode, target prompt, mirrored part); the second set edits the same sources (same seeds) again
EDITS = (("swap", "a person waves their left hand", "none"), ("mirror", "", "all"))
EDITS_AGAIN = (("swap", "a person raises their right hand", "none"), ("mirror", "", "upper"))
CONTROL_PROMPT = "a person walks forward"
CONTROLS = ("circle", "turn-left")          # path presets at 1 m/s
CONTROL_SECONDS = 4.0                       # (or the model's longest motion)
WORDS = ("waves", "right", "hand")          # picked in turn in the first prompt's attention maps
CFG = 7.5
# (label, report key, target in seconds or None), in the order the table prints them
ROWS = (("generate → preview video", "generate_s", GENERATE_TARGET_S),
        ("generate → full video", "generate_full_s", None),
        ("edit → preview side-by-side", "edit_first_s", EDIT_TARGET_S),
        ("edit → full side-by-side", "edit_first_full_s", None),
        ("edit again, same source → preview", "edit_same_source_s", EDIT_TARGET_S),
        ("edit again, same source → full", "edit_same_source_full_s", None),
        ("edit this motion → preview", "edit_generated_s", EDIT_TARGET_S),
        ("edit this motion → full", "edit_generated_full_s", None),
        ("control (path) → preview video", "control_s", CONTROL_TARGET_S),
        ("control (path) → full video", "control_full_s", None),
        ("word click → heatmap", "word_click_s", WORD_TARGET_S))


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


def _video_url(value) -> str:
    """The URL of a Video output as gradio_client returns it without downloading (a FileData dict,
    or {"video": FileData, ...})."""
    data = value.get("video", value) if isinstance(value, dict) else None
    if not isinstance(data, dict) or not data.get("url"):
        raise RuntimeError(f"no video URL in the response: {value!r:.200}")
    return data["url"]


def _wait_for_render_workers(count: int) -> None:
    """The timings are of the studio at work, not of its render workers starting (the server's
    warm-up thread starts them)."""
    from salad.render.workers import wait_ready

    try:
        wait_ready(count)
    except (TimeoutError, RuntimeError) as exc:
        raise SystemExit(f"the studio's {exc}") from None


def run(model: str | None, steps: int | None, sampler: str, precision: str, threads: int | None,
        fetch_all: bool = False, render_workers: int = 1) -> dict:
    """sampler "auto": the studio's defaults for text and for guided control; steps=None: each sampler's
    default (salad.pipeline.DEFAULT_STEPS), else these steps for both. fetch_all: download every file a
    response returns, not just its video."""
    from gradio_client import Client

    from .server import create_app, launch
    from .settings import Settings

    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(model=model, port=_free_port(), tmp_dir=Path(tmp), precision=precision, threads=threads,
                            render_workers=render_workers)
        studio_app = create_app(settings)
        if studio_app.studio is None:
            raise SystemExit(f"the studio could not load a model: {studio_app.error}")
        studio, asked = studio_app.studio, sampler
        computed = studio.pipe.precision
        if sampler == "auto":
            sampler, editing, guided = studio.default_sampler, studio.edit_sampler, studio.control_sampler
        else:
            editing = sampler
            guided = sampler if sampler in ("ddim", "consistency") else "ddim"     # no DPM-Solver++ guidance
        try:
            # the pipeline's own check: the default steps, and a clear refusal of a student the model lacks
            guided_steps = studio.pipe.check_sampling(steps, CFG, guided)[0]
            edit_steps = studio.pipe.check_sampling(steps, CFG, editing)[0]
            steps, _, sampler, _ = studio.pipe.check_sampling(steps, CFG, sampler)
        except ValueError as exc:
            studio_app.close()
            raise SystemExit(f"cannot benchmark the {sampler} sampler: {exc}") from None
        http = httpx.Client(timeout=300)
        try:
            client = Client(launch(studio_app, settings, block=False), verbose=False,
                            download_files=tmp if fetch_all else False)

            def shown(outputs):
                """The outputs of a call whose first is the video the page plays, that video fetched."""
                if not fetch_all:
                    http.get(_video_url(outputs[0])).raise_for_status()
                return outputs

            def generate(prompt: str, seed: int):
                return shown(client.predict(prompt, True, 4.0, seed, steps, CFG, sampler, True, api_name="/generate"))

            def edit(mode: str, target: str, mirror: str, seed: int):
                return shown(client.predict(PROMPTS[0], mode, target, None, "", 2.0, mirror, 0.2, "auto", True, 4.0,
                                            seed, edit_steps, CFG, editing, True, api_name="/edit"))

            path_seconds = min(CONTROL_SECONDS, float(studio_app.studio.pipe.max_seconds))

            def control(preset: str, seed: int):
                return shown(client.predict(CONTROL_PROMPT, "path", preset, path_seconds, 1.0, None, "", "first, last",
                                            1.0, seed, guided_steps, CFG, True, guided, api_name="/control"))

            def two_steps(call, video_api: str) -> tuple[float, float]:
                """(seconds to the preview, seconds to the full video: the preview call plus the video call)."""
                preview = _timed(call)
                return preview, preview + _timed(lambda: shown(client.predict("cm", api_name=video_api)))

            def series(calls, video_api: str) -> tuple[list[float], list[float]]:
                times = [two_steps(call, video_api) for call in calls]
                return [p for p, _ in times], [f for _, f in times]

            # warm-up: text encoder, kernels, renderer (with and without antialiasing), the guidance, the render workers
            _wait_for_render_workers(render_workers)
            two_steps(lambda: generate("a person walks", 99), "/generate_video")
            two_steps(lambda: control("straight", 99), "/control_video")
            # on the model thread: the studio leaves every other thread one core (app.model_thread)
            reference = [studio.model_thread.run(matmul_reference_ms)]
            report = {}
            report["generate_s"], report["generate_full_s"] = series(
                [lambda p=p: generate(p, 0) for p in PROMPTS], "/generate_video")
            report["edit_first_s"], report["edit_first_full_s"] = series(
                [lambda e=e, i=i: edit(*e, 10 + i) for i, e in enumerate(EDITS)], "/edit_video")
            report["edit_same_source_s"], report["edit_same_source_full_s"] = series(
                [lambda e=e, i=i: edit(*e, 10 + i) for i, e in enumerate(EDITS_AGAIN)], "/edit_video")

            def edit_generated(mode: str, target: str, mirror: str, seed: int) -> tuple[float, float]:
                two_steps(lambda: generate(PROMPTS[0], seed), "/generate_video")     # the motion, untimed
                source, _, auto, seconds, seed, steps_, cfg, sampler_, lock = (
                    v.get("value") if isinstance(v, dict) else v for v in client.predict(api_name="/edit_generated"))
                return two_steps(lambda: shown(client.predict(source, mode, target, None, "", 2.0, mirror, 0.2, "auto",
                                                              auto, seconds, seed, steps_, cfg, sampler_, lock,
                                                              api_name="/edit")), "/edit_video")

            times = [edit_generated(*e, 20 + i) for i, e in enumerate(EDITS)]
            report["edit_generated_s"], report["edit_generated_full_s"] = [p for p, _ in times], [f for _, f in times]
            report["control_s"], report["control_full_s"] = series(
                [lambda p=p: control(p, 0) for p in CONTROLS], "/control_video")
            report["word_click_s"] = word_clicks(client, generate(PROMPTS[0], 0))
            report["matmul_reference_ms"] = reference + [studio.model_thread.run(matmul_reference_ms)]
        finally:
            http.close()
            studio_app.close()
            remove_download_leftovers(started)
    return {"settings": {"model": model or "embedded", "steps": steps, "sampler": sampler, "asked": asked,
                         "edit_sampler": editing, "edit_steps": edit_steps, "control_sampler": guided,
                         "control_steps": guided_steps, "precision": precision, "computed": computed,
                         "threads": threads, "fetch_all": fetch_all, "render_workers": render_workers}} | report | {
            "targets_s": {"generate": GENERATE_TARGET_S, "edit": EDIT_TARGET_S, "control": CONTROL_TARGET_S,
                          "word_click": WORD_TARGET_S}}


def word_clicks(client, generated) -> list[float]:
    """Pick WORDS in turn in the attention maps of `generated` (the outputs of a "generate" call,
    the session's current motion), as the Attention tab does: after a generation the views are
    refreshed (no word), then each click asks for the word's heatmap ("attention", timed) and
    then its tinted video ("attention_video"), which still renders when the next word is picked."""
    layers, first, last = (generated[i]["value"] for i in (5, 6, 7))
    words = [label for label, _ in generated[4]["choices"]]
    client.predict(None, layers, first, last, api_name="/attention")
    times, video = [], None
    for word in WORDS:
        index = words.index(word)
        times.append(_timed(lambda: client.predict(index, layers, first, last, api_name="/attention")))
        video = client.submit(index, layers, first, last, api_name="/attention_video")
    video.result()
    return times


def format_table(report: dict) -> str:
    s = report["settings"]
    fetched = "every returned file fetched" if s.get("fetch_all") else "videos fetched"
    edit = f", edit {s['edit_sampler']}-{s['edit_steps']}" if "edit_sampler" in s else ""
    control = f", control {s['control_sampler']}-{s['control_steps']}" if "control_sampler" in s else ""
    lines = [f"studio latency, {s['model']} model, {s['sampler']}-{s['steps']}{edit}{control}, "
             f"{s['computed']} ({s['precision']}), threads {s['threads'] or 'default'}, "
             f"{s.get('render_workers', 0)} render worker(s), {fetched}"]
    if "matmul_reference_ms" in report:
        before, after = report["matmul_reference_ms"]
        lines.append(f"50 fp32 1024² matmuls: {before:.0f} ms before the requests, {after:.0f} ms after")
    lines += ["",
             f"{'request':36s} {'median s':>9s} {'max s':>7s} {'target s':>9s}  met"]
    for name, key, target in ROWS:
        times = report[key]
        med = statistics.median(times)
        met = "" if target is None else "yes" if med <= target else "NO"
        shown = "-" if target is None else f"{target:.1f}"
        lines.append(f"{name:36s} {med:9.2f} {max(times):7.2f} {shown:>9s}  {met}".rstrip())
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m app.bench", description=__doc__.splitlines()[0])
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--steps", type=int, default=None,
                   help="sampling steps (default: each sampler's, 50 for ddim and dpm, 25 for dpm-sde, 4 for "
                        "consistency)")
    p.add_argument("--sampler", choices=("auto", "dpm-sde", "ddim", "dpm", "consistency"), default="auto",
                   help="auto: the studio's defaults (text and guided control apart); consistency: the model's "
                        "distilled student")
    p.add_argument("--precision", choices=PRECISIONS, default="auto",
                   help="as the studio's --precision (default auto: bf16 autocast from 2 rows a forward where the "
                        "CPU has native bf16)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--render-workers", type=int, default=1, metavar="N",
                   help="as the studio's --render-workers (default 1)")
    p.add_argument("--fetch-all", action="store_true",
                   help="download every file a response returns (gradio_client's default), not just its video")
    p.add_argument("--out", type=Path, default=None, help="write the measurements as JSON here")
    a = p.parse_args(argv)
    report = run(a.model, a.steps, a.sampler, a.precision, a.threads, a.fetch_all, a.render_workers)
    print(format_table(report))
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
