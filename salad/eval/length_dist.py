"""How well the model chooses motion lengths by itself (MoLA Fig. 4).

For test captions the model generates with seconds="model", so each motion ends where its
activation channel drops (no band holds it to the length prior), and the lengths are compared
with the real test motions' lengths for the same captions:

* Jensen-Shannon divergence between the two length histograms (bins of `bin_frames` frames
  from 0; base-2 logarithm, so 0 = identical and 1 = disjoint);
* Earth mover's distance between the two sets of lengths, in frames (1-D Wasserstein-1 of
  the samples, no binning).

The reference is each test motion's length as the model could produce it: cut down to a
multiple of 4 and clipped to [16, canvas] frames. A fixed-length baseline (every sample at
the test mean, a multiple of 4) shows what choosing no length at all scores.

    salad eval-length --data data/bandai-hml --out DIR [--samples N]
"""
from __future__ import annotations

import io
import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from scipy.spatial.distance import jensenshannon
from scipy.stats import wasserstein_distance

from ..files import atomic_write, atomic_write_text, shown_path
from ..motion.representation import FPS

LENGTH_UNIT = 4          # the VAE's temporal downsampling: generated lengths are multiples of it
MIN_FRAMES = 16          # the pipeline's shortest auto-length motion
DEFAULT_BIN_FRAMES = 8   # two length units per bin: every bin holds the same number of reachable lengths


def _lengths(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).ravel()
    if a.size == 0:
        raise ValueError(f"{name}: no lengths")
    if not np.isfinite(a).all() or (a < 0).any():
        raise ValueError(f"{name}: lengths must be finite and non-negative")
    return a


def length_bins(max_frames: int, bin_frames: int = DEFAULT_BIN_FRAMES) -> np.ndarray:
    """Bin edges 0, b, 2b, ... up to the first edge above `max_frames`."""
    if bin_frames < 1 or max_frames < 1:
        raise ValueError(f"need positive max_frames and bin_frames, got {max_frames} and {bin_frames}")
    return np.arange(0, max_frames + bin_frames + 1, bin_frames, dtype=np.float64)


def length_histogram(lengths, edges: np.ndarray) -> np.ndarray:
    """Share of `lengths` in each bin (sums to 1); lengths past the last edge count in the last bin."""
    a = np.clip(_lengths(lengths, "lengths"), edges[0], edges[-1] - 1e-9)
    counts, _ = np.histogram(a, bins=edges)
    return counts / counts.sum()


def js_divergence(p: np.ndarray, q: np.ndarray) -> float:
    """Jensen-Shannon divergence (base 2, in [0, 1]) of two histograms over the same bins."""
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    if p.shape != q.shape or p.ndim != 1:
        raise ValueError(f"histograms must be 1-D and alike, got {p.shape} and {q.shape}")
    if (p < 0).any() or (q < 0).any() or p.sum() <= 0 or q.sum() <= 0:
        raise ValueError("histograms must be non-negative with positive mass")
    # scipy returns the distance, the square root of the divergence
    return float(jensenshannon(p, q, base=2) ** 2)


def earth_movers(a, b) -> float:
    """Earth mover's distance between two sets of lengths, in their unit (frames)."""
    return float(wasserstein_distance(_lengths(a, "a"), _lengths(b, "b")))


def compare_lengths(real, generated, edges: np.ndarray) -> dict[str, float]:
    real, generated = _lengths(real, "real lengths"), _lengths(generated, "generated lengths")
    return {"jsd": js_divergence(length_histogram(real, edges), length_histogram(generated, edges)),
            "emd_frames": earth_movers(real, generated),
            "mean_frames": float(generated.mean()), "std_frames": float(generated.std())}


def reachable_length(n: int, canvas: int) -> int:
    """A real length as the model could produce it: a multiple of 4 in [16, canvas]."""
    return int(min(max((n // LENGTH_UNIT) * LENGTH_UNIT, MIN_FRAMES), (canvas // LENGTH_UNIT) * LENGTH_UNIT))


def _content_of(labels: dict | None, name: str) -> str | None:
    if labels is None:
        return None
    entry = labels.get(name.split("@", 1)[0])
    return None if entry is None else entry.content


@torch.no_grad()
def generate_auto_length(pipe, prompts: list[str], seed: int = 0, steps: int = 50, cfg: float = 7.5,
                         sampler: str = "ddim") -> list:
    """Pipeline.generate(seconds="model") for several different prompts in one sampling run: each
    motion ends where its own activation drops (the model's lengths, before any band holds them)."""
    prompts = [pipe.check_prompt(p) for p in prompts]
    steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler, len(prompts))
    text = pipe.sampler_text(prompts, sampler)
    z = pipe.denoise(text, pipe.noise(len(prompts), pipe.canvas_frames, seed), sampler, steps, cfg, auto=True,
                     seed=seed)
    return pipe.decode(z, None, prompts, seed)


def evaluate_lengths(pipe, dataset, samples: int = 256, seed: int = 0, steps: int | None = None, cfg: float = 7.5,
                     sampler: str = "ddim", batch: int = 16, bin_frames: int = DEFAULT_BIN_FRAMES,
                     labels: dict | None = None, progress: Callable[[int, int], None] | None = None
                     ) -> dict[str, Any]:
    """Generate `samples` auto-length motions for test captions and score their lengths.

    Test motions are drawn without replacement (cycling when samples exceed the split), one
    random caption each, and generated `batch` captions per sampling run. `labels`
    ({motion id: MotionLabels}) adds per-content mean lengths.
    """
    if not isinstance(samples, int) or samples < 2:
        raise ValueError(f"samples must be an integer >= 2, got {samples!r}")
    if not isinstance(batch, int) or not 1 <= batch <= 64:
        raise ValueError(f"batch must be an integer in 1..64, got {batch!r}")
    steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler)
    items = dataset.items
    canvas = int(pipe.canvas_frames)
    rng = np.random.default_rng(seed)
    order = np.concatenate([rng.permutation(len(items)) for _ in range(-(-samples // len(items)))])[:samples]
    captions = [items[i].captions[int(rng.integers(len(items[i].captions)))] for i in order]
    chunks = [list(range(s, min(s + batch, samples))) for s in range(0, samples, batch)]

    generated = np.zeros(samples, dtype=np.int64)
    t0 = time.time()
    for c, ks in enumerate(chunks):
        motions = generate_auto_length(pipe, [captions[k] for k in ks], seed=seed * 1_000_003 + c, steps=steps,
                                       cfg=cfg, sampler=sampler)
        generated[ks] = [m.frames for m in motions]
        if progress:
            progress(c + 1, len(chunks))
    gen_time = time.time() - t0

    raw = np.array([len(items[i].features) for i in order])
    real = np.array([reachable_length(n, canvas) for n in raw])
    edges = length_bins(canvas, bin_frames)
    fixed = int(round(real.mean() / LENGTH_UNIT)) * LENGTH_UNIT
    # another draw of as many test motions: the scores of a model whose lengths were perfect
    other = np.random.default_rng([seed, 1]).choice(len(items), samples, replace=True)
    rows = {"model": compare_lengths(real, generated, edges),
            "fixed_mean_length": compare_lengths(real, np.full(samples, fixed), edges),
            "test_redraw": compare_lengths(real, [reachable_length(len(items[i].features), canvas) for i in other],
                                           edges)}
    per_content: dict[str, dict[str, float]] = {}
    contents = [_content_of(labels, items[i].name) for i in order]
    for name in sorted({c for c in contents if c is not None}):
        sel = np.array([c == name for c in contents])
        per_content[name] = {"n": int(sel.sum()), "real_mean_s": float(real[sel].mean() / FPS),
                             "generated_mean_s": float(generated[sel].mean() / FPS)}
    return {
        "rows": rows,
        "real": {"mean_frames": float(real.mean()), "std_frames": float(real.std()),
                 "raw_mean_frames": float(raw.mean()), "over_canvas": int((raw > canvas).sum())},
        # the two ends where the activation never drops (full canvas) or drops at once (the minimum)
        "generated": {"at_minimum_share": float((generated <= MIN_FRAMES).mean()),
                      "at_canvas_share": float((generated >= (canvas // LENGTH_UNIT) * LENGTH_UNIT).mean())},
        "per_content": per_content,
        "lengths": {"real": real.tolist(), "generated": generated.tolist(), "captions": captions},
        "histogram": {"edges": edges.tolist(), "real": length_histogram(real, edges).tolist(),
                      "generated": length_histogram(generated, edges).tolist()},
        "protocol": {"samples": samples, "unique_captions": len(set(captions)), "seed": seed, "steps": steps,
                     "cfg": cfg, "sampler": sampler, "batch": batch, "bin_frames": bin_frames,
                     "canvas_frames": canvas, "fixed_length_frames": fixed, "dataset": str(dataset.root),
                     "model": shown_path(getattr(pipe, "source", ""))},
        "time_s": {"generation": round(gen_time, 2), "per_sample": round(gen_time / samples, 3)},
    }


def histogram_png(results: dict[str, Any], path: str | Path, dpi: int = 120) -> Path:
    """Real vs generated length histograms (and the fixed-length baseline) as a PNG, written atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    h = results["histogram"]
    edges = np.asarray(h["edges"]) / FPS
    fig = Figure(figsize=(7.0, 3.6), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for key, label, colour in (("real", "test set", "#4c72b0"), ("generated", "generated (auto length)", "#dd8452")):
        ax.stairs(h[key], edges, label=label, color=colour, fill=key == "real", alpha=0.45 if key == "real" else 1.0,
                  linewidth=1.8)
    fixed = results["protocol"]["fixed_length_frames"] / FPS
    ax.axvline(fixed, color="#555555", linestyle="--", linewidth=1.2, label=f"fixed mean length ({fixed:.1f} s)")
    m, b = results["rows"]["model"], results["rows"]["fixed_mean_length"]
    ax.set_title(f"JSD {m['jsd']:.3f} (fixed {b['jsd']:.3f}), EMD {m['emd_frames']:.1f} frames "
                 f"(fixed {b['emd_frames']:.1f})", fontsize=10)
    ax.set_xlabel("motion length (s)")
    ax.set_ylabel("share of motions")
    ax.legend(fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", facecolor="white")
    atomic_write(path, lambda f: f.write(buf.getvalue()))
    return path


def markdown_report(results: dict[str, Any]) -> str:
    p, r = results["protocol"], results["real"]
    lines = [
        "# Generated motion lengths", "",
        f"{p['samples']} test captions ({p['unique_captions']} distinct) from `{p['dataset']}`, generated with "
        f"seconds=None ({p['sampler']}, {p['steps']} steps, cfg {p['cfg']}, seed {p['seed']}).", "",
        "| Lengths | JSD ↓ | EMD (frames) ↓ | Mean (s) | Std (s) |", "|---|---|---|---|---|",
        f"| Test set | 0 | 0 | {r['mean_frames'] / FPS:.2f} | {r['std_frames'] / FPS:.2f} |",
    ]
    for key, name in (("model", "Model (auto length)"), ("fixed_mean_length", "Fixed mean length"),
                      ("test_redraw", "Another draw of test motions (sampling floor)")):
        row = results["rows"].get(key)
        if row is None:
            continue
        lines.append(f"| {name} | {row['jsd']:.4f} | {row['emd_frames']:.2f} | {row['mean_frames'] / FPS:.2f} | "
                     f"{row['std_frames'] / FPS:.2f} |")
    lines += ["", f"JSD: Jensen-Shannon divergence (base 2) of histograms with {p['bin_frames']}-frame bins from 0 "
              f"to {p['canvas_frames']} frames. EMD: 1-D Wasserstein distance of the lengths themselves, in frames "
              f"({FPS} fps). Real lengths are cut down to multiples of 4 and clipped to [16, {p['canvas_frames']}] "
              f"frames (what the model can produce); {r['over_canvas']} of the drawn test motions are longer than "
              f"the canvas. The fixed baseline puts every sample at {p['fixed_length_frames']} frames; the "
              "sampling floor compares the drawn lengths with an independent draw (with replacement) of as many "
              "test motions, i.e. what perfectly chosen lengths would score at this sample size.", ""]
    g = results.get("generated")
    if g:
        lines += [f"{100 * g['at_minimum_share']:.1f}% of the generated motions stop at the {MIN_FRAMES}-frame "
                  f"minimum and {100 * g['at_canvas_share']:.1f}% fill the whole canvas.", ""]
    if results["per_content"]:
        lines += ["## Mean length per content", "", "| Content | n | Test set (s) | Generated (s) |",
                  "|---|---|---|---|"]
        for name, c in sorted(results["per_content"].items(), key=lambda kv: kv[1]["real_mean_s"]):
            lines.append(f"| {name} | {c['n']} | {c['real_mean_s']:.2f} | {c['generated_mean_s']:.2f} |")
        lines.append("")
    t = results["time_s"]
    lines.append(f"Generation took {t['generation']:.0f} s ({t['per_sample']:.2f} s per motion). "
                 "Histogram: lengths.png.")
    return "\n".join(lines) + "\n"


def write_length_report(results: dict[str, Any], out_dir: str | Path) -> Path:
    """results.json, report.md and lengths.png in `out_dir`; returns report.md's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    histogram_png(results, out / "lengths.png")
    path = out / "report.md"
    atomic_write_text(path, markdown_report(results))
    return path
