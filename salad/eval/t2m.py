"""The text-to-motion evaluation protocol of Guo et al. (CVPR 2022) on a HumanML3D-layout test split.

Each repeat (its own seed) shuffles the test motions, draws one caption per motion and a random window of at
most `max_frames` frames cut down to a multiple of 4, and asks the generator for a motion of that caption and
length (the last incomplete batch of 32 is dropped). The generator is called on batches of 32 motions of similar
length, not on the R-precision pools: a batch is sampled at its longest member's length, and on the Bandai test
split the pools' mixed lengths made half of the sampled frames padding (~152k frames sampled for ~73k real ones,
against ~76k when grouped by length). Per repeat:

* R-precision top-1/2/3: within each batch of 32, the texts rank the 32 generated motions by distance;
* MM-Dist: mean distance between each text and the motion generated for it;
* Diversity: mean distance of 300 random pairs of generated motions;
* FID: against the real test motions (their first `max_frames` frames, fixed across repeats);
* MultiModality: `mm_prompts` prompts generated `mm_repeats` times each, mean distance of 10 random pairs.

Results are mean and 95% confidence half-width (1.96 std / sqrt(repeats)) over the repeats.

`salad eval --real-only` scores the real test motions themselves (the "Real motion" row).

A model's 20 repeats take hours on a small CPU, so with `state_file` each finished repeat is saved and a rerun
of the same protocol and generator continues after the last one (each repeat draws from its own seed, so the
result is the one an uninterrupted run gives).
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..files import atomic_write_text
from ..diffusion.sampling import describe_settings
from ..data.dataset import MotionDataset
from ..motion.representation import FEATURE_DIM
from .metrics import (diversity, frechet_distance, gaussian_stats, matching_distance, mean_ci, multimodality,
                      r_precision)
from .sampling import fixed_crop, random_crop

Generator = Callable[[list[str], list[int]], list[np.ndarray]]

METRICS = ("R_precision_top1", "R_precision_top2", "R_precision_top3", "FID", "MM_Dist", "Diversity",
           "MultiModality")
# lower is better for FID and MM-Dist; Diversity and MultiModality are judged against the real motions
_HIGHER_BETTER = {"R_precision_top1", "R_precision_top2", "R_precision_top3"}


class GroundTruth:
    """A generator that returns real motions: the protocol passes the windows it drew as `references`.

    Called without references (outside the protocol), it returns for each caption a real motion that has it,
    cropped to the requested length.
    """

    uses_references = True

    def __init__(self, dataset: MotionDataset | None = None, seed: int = 0):
        self.dataset = dataset
        self.rng = np.random.default_rng(seed)

    def __call__(self, captions: list[str], lengths: list[int],
                 references: Sequence[np.ndarray] | None = None) -> list[np.ndarray]:
        if references is not None:
            return [np.asarray(r)[:n] for r, n in zip(references, lengths)]
        if self.dataset is None:
            raise ValueError("the ground-truth generator needs a dataset to look captions up in")
        out = []
        for cap, n in zip(captions, lengths):
            found = [it.features for it in self.dataset.items if cap in it.captions and len(it.features) >= n]
            if not found:
                raise ValueError(f"no real motion of at least {n} frames has the caption {cap!r}")
            f = found[int(self.rng.integers(len(found)))]
            start = int(self.rng.integers(0, len(f) - n + 1))
            out.append(f[start:start + n])
        return out


def ground_truth_generator(dataset: MotionDataset | None = None) -> GroundTruth:
    """The "Real motion" row: a generator returning the real motions the protocol drew."""
    return GroundTruth(dataset)


def _generate(generate: Generator, captions: list[str], lengths: list[int],
              references: list[np.ndarray] | None = None) -> list[np.ndarray]:
    if getattr(generate, "uses_references", False):
        out = generate(captions, lengths, references=references)
    else:
        out = generate(captions, lengths)
    if not isinstance(out, (list, tuple)) or len(out) != len(captions):
        got = len(out) if isinstance(out, (list, tuple)) else type(out).__name__
        raise ValueError(f"generator returned {got} motions for {len(captions)} prompts (expected a list)")
    checked = []
    for i, (m, n) in enumerate(zip(out, lengths)):
        a = np.asarray(m.detach().cpu().numpy() if hasattr(m, "detach") else m, dtype=np.float32)
        if a.shape != (n, FEATURE_DIM):
            raise ValueError(f"generator output {i} for {captions[i]!r} has shape {a.shape}, expected ({n}, {FEATURE_DIM})")
        if not np.isfinite(a).all():
            raise ValueError(f"generator output {i} for {captions[i]!r} contains NaN or infinite values")
        checked.append(a)
    return checked


def _as_dataset(dataset: MotionDataset | str | Path, split: str = "test") -> MotionDataset:
    if isinstance(dataset, MotionDataset):
        return dataset
    return MotionDataset(dataset, split, max_frames=10 ** 9)


def _load_state(path: Path | None, fingerprint: dict) -> dict:
    """Finished repeats of an earlier run with the same fingerprint (else none)."""
    empty = {"fingerprint": fingerprint, "repeats": []}
    if path is None or not path.exists():
        return empty
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable evaluation state ({e}); delete it to start over") from None
    return state if state.get("fingerprint") == fingerprint else empty


def evaluate_t2m(generate: Generator, dataset: MotionDataset | str | Path, evaluator, repeats: int = 20,
                 batch_size: int = 32, mm_prompts: int = 100, mm_repeats: int = 30, seed: int = 0,
                 max_frames: int = 196, diversity_pairs: int = 300, mm_pairs: int = 10,
                 progress: bool = False, state_file: str | Path | None = None) -> dict[str, Any]:
    """Run the protocol; `dataset` is a MotionDataset (its items are used as the test set) or a directory
    (its test split). MultiModality is skipped for the ground-truth generator and when mm_prompts = 0.
    `state_file` (JSON) keeps finished repeats so that an interrupted run resumes."""
    if repeats < 1 or batch_size < 2:
        raise ValueError(f"need repeats >= 1 and batch_size >= 2, got {repeats} and {batch_size}")
    ds = _as_dataset(dataset)
    items = ds.items
    n_batches = len(items) // batch_size
    if n_batches == 0:
        raise ValueError(f"{ds.root}: {len(items)} motions are fewer than one batch of {batch_size}")
    t_start = time.time()
    reference = evaluator.embed_motions([fixed_crop(it.features, max_frames) for it in items])
    ref_stats = gaussian_stats(reference)
    is_real = getattr(generate, "uses_references", False)
    do_mm = mm_prompts > 0 and mm_repeats >= 2 and not is_real
    protocol = {"batch_size": batch_size, "motions_per_repeat": n_batches * batch_size,
                "max_frames": max_frames, "diversity_pairs": diversity_pairs,
                "mm_prompts": mm_prompts if do_mm else 0, "mm_repeats": mm_repeats if do_mm else 0,
                "mm_pairs": mm_pairs, "seed": seed, "dataset": str(ds.root), "ground_truth": bool(is_real),
                "generation_batches": "by length"}
    state_path = Path(state_file) if state_file is not None else None
    describe = getattr(generate, "describe", None)
    generator = describe() if describe else None
    state = _load_state(state_path, {"protocol": protocol, "generator": generator, "motions": len(items)})
    done = state["repeats"][:repeats]
    values: dict[str, list[float]] = {m: [v[m] for v in done if m in v] for m in METRICS}
    gen_time = sum(v.get("generation_s", 0.0) for v in done)
    if done and hasattr(generate, "calls"):
        generate.calls = done[-1].get("calls", state.get("calls", 0))   # its seeds follow its call count
    if done and progress:
        print(f"resuming after {len(done)} finished repeats from {state_path}", flush=True)
    for r in range(len(done), repeats):
        gen_before = gen_time
        rng = np.random.default_rng([seed, r])
        order = rng.permutation(len(items))[:n_batches * batch_size]
        captions = [items[i].captions[int(rng.integers(len(items[i].captions)))] for i in order]
        windows = [random_crop(items[i].features, max_frames, rng) for i in order]
        lengths = [len(w) for w in windows]
        motions: list[np.ndarray] = [None] * len(order)
        by_length = sorted(range(len(order)), key=lambda i: lengths[i])
        t0 = time.time()
        for s in range(0, len(order), batch_size):
            idx = by_length[s:s + batch_size]
            out = _generate(generate, [captions[i] for i in idx], [lengths[i] for i in idx], [windows[i] for i in idx])
            for i, m in zip(idx, out):
                motions[i] = m
        gen_time += time.time() - t0
        m_emb = evaluator.embed_motions(motions)
        t_emb = evaluator.embed_texts(captions)
        top = r_precision(t_emb, m_emb, pool=batch_size)
        for k in range(3):
            values[f"R_precision_top{k + 1}"].append(float(top[k]))
        values["MM_Dist"].append(matching_distance(t_emb, m_emb))
        values["Diversity"].append(diversity(m_emb, diversity_pairs, rng))
        values["FID"].append(frechet_distance(*gaussian_stats(m_emb), *ref_stats))
        if do_mm:
            t0 = time.time()
            picks = rng.choice(len(items), min(mm_prompts, len(items)), replace=False)
            mm_emb = []
            for i in picks:
                cap = items[i].captions[int(rng.integers(len(items[i].captions)))]
                n = len(random_crop(items[i].features, max_frames, rng))
                gens: list[np.ndarray] = []
                for s in range(0, mm_repeats, batch_size):
                    k = min(batch_size, mm_repeats - s)
                    gens += _generate(generate, [cap] * k, [n] * k)
                mm_emb.append(evaluator.embed_motions(gens))
            gen_time += time.time() - t0
            values["MultiModality"].append(multimodality(np.stack(mm_emb), mm_pairs, rng))
        if state_path is not None:
            record = {m: v[r] for m, v in values.items() if len(v) > r}
            record.update(generation_s=gen_time - gen_before, calls=getattr(generate, "calls", 0))
            state["repeats"] = state["repeats"][:r] + [record]
            atomic_write_text(state_path, json.dumps(state))
        if progress:
            print(f"repeat {r + 1}/{repeats}: top1 {top[0]:.3f} FID {values['FID'][-1]:.4f} "
                  f"({time.time() - t_start:.0f} s)", flush=True)
    metrics = {}
    for name, v in values.items():
        if v:
            mean, ci = mean_ci(v)
            metrics[name] = {"mean": mean, "ci95": ci, "values": v}
    return {
        "metrics": metrics,
        "reference": {"motions": len(items), "Diversity": diversity(reference, diversity_pairs,
                                                                    np.random.default_rng(seed))},
        "protocol": {"repeats": repeats, **protocol},
        "generator": generator,
        "time_s": {"total": round(time.time() - t_start, 2), "generation": round(gen_time, 2)},
    }


def _rows(results: Mapping[str, Any]) -> dict[str, dict]:
    if "metrics" in results:
        return {"Real motion" if results.get("protocol", {}).get("ground_truth") else "Model": dict(results)}
    for name, r in results.items():
        if not isinstance(r, Mapping) or "metrics" not in r:
            raise ValueError(f"report row {name!r} is not an evaluate_t2m result")
    return {name: dict(r) for name, r in results.items()}


def _fmt(mean: float, ci: float) -> str:
    # unit-norm embeddings make the FID of good models tiny: keep significant digits instead of zeros
    if mean == 0 or abs(mean) >= 0.01:
        return f"{mean:.4f} ± {ci:.4f}"
    return f"{mean:.2e} ± {ci:.1e}"


def markdown_table(results: Mapping[str, Any]) -> str:
    """One row per method: mean ± 95% CI of every metric present."""
    rows = _rows(results)
    present = [m for m in METRICS if any(m in r["metrics"] for r in rows.values())]
    head = "| Method | Repeats | " + " | ".join(m.replace("_", " ") + (" ↑" if m in _HIGHER_BETTER else "") for m in present) + " |"
    lines = [head, "|" + "---|" * (len(present) + 2)]
    for name, r in rows.items():
        cells = []
        for m in present:
            v = r["metrics"].get(m)
            cells.append("-" if v is None else _fmt(v["mean"], v["ci95"]))
        lines.append(f"| {name} | {r.get('protocol', {}).get('repeats', '?')} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(results: Mapping[str, Any], out_dir: str | Path, title: str = "Text-to-motion evaluation") -> Path:
    """Write results.json and report.md into `out_dir`; `results` is one evaluate_t2m result or a mapping
    {method name: result}. Returns the Markdown file's path."""
    out = Path(out_dir)
    rows = _rows(results)
    atomic_write_text(out / "results.json", json.dumps(rows, indent=2))
    first = next(iter(rows.values()))
    p = first.get("protocol", {})
    ref = first.get("reference", {})
    notes = [
        f"# {title}", "",
        markdown_table(rows), "",
        f"Protocol: each repeat draws {p.get('motions_per_repeat')} test motions from "
        f"`{p.get('dataset')}` in batches of {p.get('batch_size')} (R-precision pools"
        f"{'; generated in batches of similar length' if p.get('generation_batches') == 'by length' else ''}), "
        f"one random caption per motion, windows of at most {p.get('max_frames')} frames cut to multiples of 4; FID against the "
        f"{ref.get('motions')} real test motions (Diversity of those: {ref.get('Diversity', float('nan')):.4f}); "
        f"Diversity over {p.get('diversity_pairs')} pairs; values are mean ± 1.96·std/√repeats.",
        "Embeddings are unit-norm, so distances lie in [0, 2]; numbers are not comparable with evaluators "
        "trained on other data or with unnormalised embeddings.",
    ]
    mm = next((r["protocol"] for r in rows.values() if r.get("protocol", {}).get("mm_prompts")), None)
    if mm:
        notes.append(f"MultiModality: {mm.get('mm_prompts')} prompts × {mm.get('mm_repeats')} generations, "
                     f"{mm.get('mm_pairs')} pairs per prompt.")
    for name, r in rows.items():
        g = r.get("generator")
        if g and "sampler" in g:
            notes.append(f"{name}: {g['sampler']} sampler{describe_settings(g)}, {g['steps']} steps, CFG {g['cfg']:g}, "
                         f"{'bf16' if g.get('bf16') else 'fp32'}, seed {g['seed']}.")
    path = out / "report.md"
    atomic_write_text(path, "\n".join(notes) + "\n")
    return path
