"""`salad bench`: speed of generation on this machine, measured, never assumed.

For each model (the embedded one, and the paper-size denoiser with random weights)
and precision (fp32, bf16) it times text -> joints for a 6 s motion (120 frames,
50 DDIM steps, classifier-free guidance) at batch 1 and 16, in a fresh subprocess so
that peak memory is that configuration's own. It also measures this machine's matmul
peak in the same run, the denoiser's achieved GFLOP/s, DPM-Solver++ against DDIM at
matched accuracy, the consistency student's 1-4 step sampling beside a fixed matmul
reference (50 fp32 1024x1024 matmuls), the student and DDIM-50 again with the networks compiled
(Pipeline.compile), and a profile of where the time goes.
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

SECONDS = 6.0   # 120 frames
CONSISTENCY_STEPS = (1, 2, 4)
CONSISTENCY_TARGET_MS = 60.0   # per 6 s motion, fp32, batch 1
PROMPT = "a person walks forward and waves their right hand"


def matmul_peak(dtype: torch.dtype, n: int = 2048, repeats: int = 5) -> float:
    """GFLOP/s of a large square matmul."""
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 2 * n ** 3 / best / 1e9


def _paper_pipeline(bf16: bool):
    """The paper-size denoiser (d=256, 8 heads, 5 layers) with random weights around the
    embedded VAE and text encoder, or tiny stand-ins when no model is installed."""
    from .diffusion.schedule import NoiseSchedule
    from .models.denoiser import Denoiser, DenoiserConfig
    from .models.text import load_text_encoder
    from .models.vae import MotionVAE
    from .motion.representation import Normalizer
    from .pipeline import Pipeline
    import numpy as np
    enc = load_text_encoder("minilm")
    torch.manual_seed(0)
    den = Denoiser(DenoiserConfig(text_dim=enc.dim))
    norm = Normalizer(np.zeros(263, np.float32), np.ones(263, np.float32))
    return Pipeline(MotionVAE(), norm, 1.0, den, enc, NoiseSchedule(), canvas_frames=196, bf16=bf16,
                    bf16_min_rows=1, device="cpu")


def _load(model: str, bf16: bool):
    """On the CPU: the bench measures this machine's CPU (its matmul peak, threads and memory). It times
    the sampler and one decode: the latent projection and the planted-feet refinement after it are
    post-processing (the refinement alone costs about a second per walk), off here. A bf16 row runs
    every forward in bf16, one-row forwards included (the library's default leaves those in fp32)."""
    from .pipeline import load_pipeline
    pipe = _paper_pipeline(bf16) if model == "paper" else load_pipeline(
        None if model == "embedded" else model, bf16=bf16, bf16_min_rows=1, device="cpu")
    pipe.set_projections(0)
    pipe.set_foot_refine(0)
    return pipe


def matmul_reference_ms(n: int = 1024, count: int = 50, repeats: int = 3) -> float:
    """Milliseconds for `count` fp32 n x n matmuls on this CPU: a yardstick measured in the same
    run as the sampling times, so that they can be compared across machines."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(count):
            a @ b
        best = min(best, time.perf_counter() - t)
    return 1000 * best


def _denoiser_flops(pipe, batch: int, seconds: float, sampler: str = "ddim") -> float:
    """FLOPs of one sampling step's forward: the CFG batch (2 x batch rows), or batch rows for
    the consistency student, whose guidance is an input."""
    from torch.utils.flop_counter import FlopCounterMode
    text = pipe.sampler_text(["a person walks"] * batch, sampler)
    rows = text.tokens.shape[0]
    x = torch.randn(rows, pipe.frames_for(seconds) // 4, 7, pipe.denoiser.config.latent_dim)
    t = torch.full((rows,), 500)
    fn = pipe.student_fn(text, False, 7.5) if sampler == "consistency" else pipe.model_fn(text, auto=False)
    with FlopCounterMode(display=False) as fc, torch.no_grad():
        fn(x, t)
    return float(fc.get_total_flops())


def run_one(model: str, bf16: bool, batch: int, sampler: str = "ddim", steps: int = 50, repeats: int = 3,
            seconds: float = SECONDS) -> dict:
    """Time one configuration in this process (called in a subprocess by `bench`)."""
    pipe = _load(model, bf16)
    if bf16 and not pipe.bf16:
        return {"skipped": "bf16 is not supported on this CPU"}
    if sampler == "consistency" and pipe.student is None:
        return {"skipped": "the model has no consistency student"}
    pipe.generate(PROMPT, seconds=seconds, steps=2, sampler=sampler, batch=batch)      # warm-up: caches, kernels
    best = _best_time(pipe, sampler, steps, batch, repeats, seconds)
    flops = _denoiser_flops(pipe, batch, seconds, sampler) * steps
    return {"model": model, "precision": "bf16" if bf16 else "fp32", "batch": batch, "sampler": sampler,
            "timed": "sampling and one decode (no latent projection, no planted-feet refinement)",
            "steps": steps, "seconds_per_call": best, "ms_per_motion": 1000 * best / batch,
            "motions_per_s": batch / best, "denoiser_gflops": flops / 1e9,
            "achieved_gflop_s": flops / best / 1e9,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "params_m": sum(p.numel() for p in pipe.denoiser.parameters()) / 1e6}


def _best_time(pipe, sampler: str, steps: int, batch: int, repeats: int, seconds: float) -> float:
    times = []
    for r in range(repeats):
        t = time.perf_counter()
        pipe.generate(PROMPT, seconds=seconds, seed=r, steps=steps, sampler=sampler, batch=batch)
        times.append(time.perf_counter() - t)
    return min(times)


def run_compiled(repeats: int = 5, seconds: float = SECONDS) -> dict:
    """The embedded model's student rows (CONSISTENCY_STEPS) and DDIM-50 after Pipeline.compile, fp32,
    batch 1, in this process (called in a subprocess by `bench`): the first call pays the compiling."""
    pipe = _load("embedded", False)
    pipe.compile()
    first = {}
    for sampler in (("consistency",) if pipe.student is not None else ()) + ("ddim",):
        t = time.perf_counter()
        pipe.generate(PROMPT, seconds=seconds, steps=2, sampler=sampler)
        first[sampler] = time.perf_counter() - t
    rows = [{"sampler": "consistency", "steps": k,
             "ms_per_motion": 1000 * _best_time(pipe, "consistency", k, 1, repeats, seconds)}
            for k in (CONSISTENCY_STEPS if pipe.student is not None else ())]
    rows.append({"sampler": "ddim", "steps": 50,
                 "ms_per_motion": 1000 * _best_time(pipe, "ddim", 50, 1, min(repeats, 3), seconds)})
    return {"first_call_s": first, "rows": rows, "timed": "as the uncompiled rows, after a first call per sampler "
            "that compiled the networks it runs (first_call_s, a 2-step generation included)"}


def solver_accuracy(model: str, bf16: bool, seeds: int = 4, ddim_steps=(10, 20, 50), dpm_steps=(5, 8, 10, 15, 20, 25, 30, 40),
                    reference_steps: int = 250) -> dict:
    """Mean joint error (m) of each sampler setting against a 250-step DDIM solution of the
    same noise: how closely each one solves the same ODE."""
    import numpy as np
    pipe = _load(model, bf16)
    pipe.set_sampling(ddim_eta=0.0, cfg_cutoff=0.0)   # the solvers of one smooth ODE, as measured before
    ref = [pipe.generate(PROMPT, seconds=SECONDS, seed=s, steps=reference_steps).joints for s in range(seeds)]

    def err(sampler, steps):
        out = [pipe.generate(PROMPT, seconds=SECONDS, seed=s, steps=steps, sampler=sampler).joints
               for s in range(seeds)]
        return float(np.mean([np.linalg.norm(o - r, axis=-1).mean() for o, r in zip(out, ref)]))

    table = {f"ddim-{k}": err("ddim", k) for k in ddim_steps}
    table.update({f"dpm-{k}": err("dpm", k) for k in dpm_steps})
    target = table["ddim-50"]
    matched = next((k for k in dpm_steps if table[f"dpm-{k}"] <= target), None)
    return {"error_vs_ddim250_m": table, "dpm_steps_matching_ddim50": matched}


def profile(model: str, bf16: bool, top: int = 12) -> list[dict]:
    """Where one batch-1 generation spends its time, by operator."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as tprofile
    pipe = _load(model, bf16)
    pipe.generate("a person walks", seconds=SECONDS, steps=2)
    with tprofile(activities=[ProfilerActivity.CPU]) as prof:
        pipe.generate("a person walks forward", seconds=SECONDS, steps=50)
    rows = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)[:top]
    total = sum(e.self_cpu_time_total for e in prof.key_averages())
    return [{"op": e.key, "self_ms": e.self_cpu_time_total / 1000, "share": e.self_cpu_time_total / total,
             "calls": e.count} for e in rows]


def _subprocess(fn: str, **kw) -> dict:
    code = (f"import json, sys; from salad.bench import {fn}; "
            f"print('RESULT' + json.dumps({fn}(**json.loads(sys.argv[1]))))")
    out = subprocess.run([sys.executable, "-c", code, json.dumps(kw)], capture_output=True, text=True,
                         env={**os.environ})
    line = next((l for l in out.stdout.splitlines() if l.startswith("RESULT")), None)
    if line is None:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"exit {out.returncode}"}
    return json.loads(line[6:])


def bench(out: Path, models=("embedded", "paper"), batches=(1, 16), quick: bool = False,
          seconds: float = SECONDS) -> dict:
    from .precision import bf16_supported
    # without native bf16 (e.g. AVX2-only CPUs) a bf16 matmul is emulated ~100x slower than fp32, and the
    # pipeline runs in fp32 anyway: there is no bf16 peak to measure
    peak = {"fp32": matmul_peak(torch.float32),
            "bf16": matmul_peak(torch.bfloat16) if bf16_supported() else None}
    runs = []
    for model in models:
        for bf16 in (False, True):
            for batch in batches:
                r = _subprocess("run_one", model=model, bf16=bf16, batch=batch, repeats=1 if quick else 3,
                                seconds=seconds)
                r.update(model=model, precision="bf16" if bf16 else "fp32", batch=batch)
                if "achieved_gflop_s" in r and peak[r["precision"]]:
                    r["share_of_matmul_peak"] = r["achieved_gflop_s"] / peak[r["precision"]]
                runs.append(r)
    report = {"machine": {"cores": os.cpu_count(), "torch": torch.__version__, "threads": torch.get_num_threads(),
                          "matmul_peak_gflop_s": peak, "matmul_1024_x50_ms": matmul_reference_ms()},
              "motion": {"seconds": seconds, "cfg": 7.5}, "runs": runs}
    if "embedded" in models:
        report["consistency"] = [_subprocess("run_one", model="embedded", bf16=False, batch=1, sampler="consistency",
                                             steps=k, repeats=1 if quick else 5, seconds=seconds)
                                 for k in CONSISTENCY_STEPS]
        report["compiled"] = _subprocess("run_compiled", repeats=1 if quick else 5, seconds=seconds)
        # the teacher as the studio samples text by default (app.studio.Studio)
        from .pipeline import DEFAULT_STEPS
        report["studio_standard"] = _subprocess("run_one", model="embedded", bf16=False, batch=1, sampler="dpm-sde",
                                                steps=DEFAULT_STEPS["dpm-sde"], repeats=1 if quick else 3,
                                                seconds=seconds)
    if "embedded" in models:
        acc = _subprocess("solver_accuracy", model="embedded", bf16=False, seeds=2 if quick else 4)
        report["solver_accuracy"] = acc
        k, matched = acc.get("dpm_steps_matching_ddim50"), True
        table = acc.get("error_vs_ddim250_m", {})
        if not k and table:     # none matched: time the most accurate setting, and say it did not match
            k = int(min((v, n) for n, v in table.items() if n.startswith("dpm-"))[1].split("-")[1])
            matched = False
        if k:
            for bf16 in (False, True):
                fast = _subprocess("run_one", model="embedded", bf16=bf16, batch=1, sampler="dpm", steps=k,
                                   repeats=1 if quick else 3)
                fast["matched_ddim50"] = matched
                report.setdefault("fast_solver", []).append(fast)
        # fp32: the faster precision at batch 1 on this CPU (see the runs above)
        report["profile_embedded_fp32_batch1"] = _subprocess("profile", model="embedded", bf16=False)
    out.parent.mkdir(parents=True, exist_ok=True)
    from .files import atomic_write_text
    atomic_write_text(out, json.dumps(report, indent=2))
    return report


def format_table(report: dict) -> str:
    peak = report["machine"]["matmul_peak_gflop_s"]
    bf16 = "not supported on this CPU" if peak["bf16"] is None else f"{peak['bf16']:.0f} GFLOP/s"
    ref = report["machine"].get("matmul_1024_x50_ms")
    lines = [f"matmul peak: fp32 {peak['fp32']:.0f} GFLOP/s, bf16 {bf16} ({report['machine']['cores']} cores)"
             + (f"; 50 fp32 1024x1024 matmuls: {ref:.0f} ms" if ref else ""), "",
             f"{'model':10s} {'prec':5s} {'batch':>5s} {'ms/motion':>10s} {'motions/s':>10s} {'GFLOP/s':>8s} "
             f"{'% peak':>7s} {'peak MB':>8s}"]
    for r in report["runs"]:
        if "ms_per_motion" not in r:
            lines.append(f"{r['model']:10s} {r['precision']:5s} {r['batch']:>5d}  {r.get('error') or r.get('skipped')}")
            continue
        lines.append(f"{r['model']:10s} {r['precision']:5s} {r['batch']:>5d} {r['ms_per_motion']:>10.0f} "
                     f"{r['motions_per_s']:>10.2f} {r['achieved_gflop_s']:>8.1f} "
                     f"{100 * r['share_of_matmul_peak']:>6.1f}% {r['peak_rss_mb']:>8.0f}")
    acc = report.get("solver_accuracy")
    if acc and "error_vs_ddim250_m" in acc:
        lines += ["", "sampler accuracy (deterministic DDIM, eta 0; mean joint error vs a 250-step DDIM solution of the "
                  "same noise):"]
        lines += [f"  {k:8s} {1000 * v:7.1f} mm" for k, v in acc["error_vs_ddim250_m"].items()]
        lines.append(f"  DPM-Solver++ steps matching DDIM-50: {acc.get('dpm_steps_matching_ddim50')}")
    for fast in report.get("fast_solver", []):
        if "ms_per_motion" in fast:
            note = "" if fast.get("matched_ddim50") else " (the most accurate DPM setting; none matched DDIM-50)"
            lines.append(f"  embedded {fast['precision']} batch 1 with dpm-{fast['steps']}: "
                         f"{fast['ms_per_motion']:.0f} ms/motion{note}")
    standard = report.get("studio_standard")
    if standard:
        lines += ["", "the teacher as the studio samples text (embedded, fp32, batch 1):"]
        lines.append(f"  dpm-sde {standard['steps']} steps: {standard['ms_per_motion']:.0f} ms/motion"
                     if "ms_per_motion" in standard else f"  {standard.get('error') or standard.get('skipped')}")
    student = report.get("consistency") or []
    if student:
        lines += ["", f"consistency student (embedded, fp32, batch 1, {report['motion']['seconds']:g} s motion; "
                      f"target <= {CONSISTENCY_TARGET_MS:g} ms):"]
    for r in student:
        if "ms_per_motion" not in r:
            lines.append(f"  {r.get('error') or r.get('skipped')}")
            break
        met = "meets" if r["ms_per_motion"] <= CONSISTENCY_TARGET_MS else "misses"
        vs = f", {r['ms_per_motion'] / ref:.2f}x the matmul reference" if ref else ""
        lines.append(f"  {r['steps']} step(s): {r['ms_per_motion']:.0f} ms/motion{vs} ({met} the target)")
    compiled = report.get("compiled")
    if compiled:
        lines += ["", "compiled (Pipeline.compile, salad --compile; embedded, fp32, batch 1):"]
        if "rows" not in compiled:
            lines.append(f"  {compiled.get('error')}")
        else:
            lines.append("  first call, compiling included: " + ", ".join(
                f"{k} {v:.0f} s" for k, v in compiled["first_call_s"].items()))
            for r in compiled["rows"]:
                met = ""
                if r["sampler"] == "consistency":
                    met = " (meets the target)" if r["ms_per_motion"] <= CONSISTENCY_TARGET_MS else " (misses the target)"
                vs = f", {r['ms_per_motion'] / ref:.2f}x the matmul reference" if ref else ""
                lines.append(f"  {r['sampler']} {r['steps']} step(s): {r['ms_per_motion']:.0f} ms/motion{vs}{met}")
    prof = report.get("profile_embedded_fp32_batch1")
    if isinstance(prof, list):
        lines += ["", "where the time goes (embedded, fp32, batch 1, 50 steps):"]
        lines += [f"  {p['op'][:40]:40s} {p['self_ms']:8.1f} ms {100 * p['share']:5.1f}%" for p in prof]
    return "\n".join(lines)
