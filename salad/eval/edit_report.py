"""Summaries and the Markdown report of the editing benchmark (salad.eval.edit_bench).

Layout of the results: "summary" {group: {edit, baseline, delta: {metric: {mean, ci95, n}}, verdict}},
"per_case" {case: the same}, "reweight" {case: amplitude per scale, Spearman rho, monotonic rate, ...}
and "reweight_overall". Means carry 95% confidence half-widths 1.96·std/√n over cases × seeds.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..files import atomic_write_text
from ..diffusion.sampling import describe_settings
from .edit_suite import REWEIGHT_BOUNDS, TARGET_HEIGHT_SLACK
from .metrics import mean_ci

SUCCESS = ("success", "classifier_ok", "physics_ok")
# preservation measures with the direction that is better: +1 higher, -1 lower
PRESERVATION = (("label_kept", 1), ("root_dist_m", -1), ("timing_corr", 1), ("pose_mpjpe_m", -1))
MIRROR_TARGET = 0.95

_TITLES = {"success": "Success ↑", "classifier_ok": "Classifier ↑", "physics_ok": "Physics ↑",
           "label_kept": "Label kept ↑", "root_dist_m": "Root dist (m) ↓", "timing_corr": "Timing corr ↑",
           "pose_mpjpe_m": "Pose MPJPE (m) ↓"}


def stat(values) -> dict[str, float] | None:
    """{mean, ci95, n} of the values that are not None (booleans count as 0/1), or None if there are none."""
    v = [float(x) for x in values if x is not None]
    if not v:
        return None
    mean, ci = mean_ci(v)
    return {"mean": mean, "ci95": ci, "n": len(v)}


def _scale_key(s: float) -> str:
    return f"{s:g}"


def _block(records: list[dict]) -> dict[str, Any]:
    out: dict[str, Any] = {"n": len(records),
                           "source_matches_prompt": stat([r["source_matches_prompt"] for r in records])}
    names = SUCCESS + tuple(m for m, _ in PRESERVATION)
    for method in ("edit", "baseline"):
        out[method] = {m: stat([r[method][m] for r in records]) for m in names}
    out["delta"] = {m: stat([float(r["edit"][m]) - float(r["baseline"][m]) for r in records
                             if r["edit"][m] is not None and r["baseline"][m] is not None]) for m in names}
    out["verdict"] = verdict(out)
    return out


def verdict(block: dict[str, Any]) -> dict[str, Any]:
    """Does attention editing preserve more than plain regeneration, at equal or higher success?

    A measure counts as better when the paired mean difference (edit - baseline) points the right way;
    "clearly" when the difference also exceeds its 95% CI.
    """
    measures, better, clearly = [], [], []
    for m, sign in PRESERVATION:
        d = block["delta"].get(m)
        if d is None:
            continue
        measures.append(m)
        if sign * d["mean"] > 0:
            better.append(m)
            if sign * d["mean"] > d["ci95"]:
                clearly.append(m)
    e, b = block["edit"]["success"], block["baseline"]["success"]
    success_not_lower = e is not None and b is not None and e["mean"] >= b["mean"]
    preserves_more = len(better) > len(measures) / 2
    if preserves_more and success_not_lower:
        text = f"yes: better on {len(better)}/{len(measures)} preservation measures at equal or higher success"
    elif preserves_more:
        text = f"preserves more ({len(better)}/{len(measures)} measures) but succeeds less often"
    else:
        text = f"no: better on only {len(better)}/{len(measures)} preservation measures"
    return {"preserves_more": preserves_more, "success_not_lower": success_not_lower,
            "better_on": better, "clearly_better_on": clearly, "measures": measures, "text": text}


def _reweight_case(records: list[dict], scales: Sequence[float]) -> dict[str, Any]:
    per = {m: {_scale_key(s): stat([r[m][k] for r in records]) for k, s in enumerate(scales)}
           for m in ("amplitude", "root_dist_m", "timing_corr", "pose_mpjpe_m")}
    return {"n": len(records), "amplitude": per["amplitude"],
            "source_amplitude": stat([r["source_amplitude"] for r in records]),
            "baseline_amplitude": stat([r["baseline_amplitude"] for r in records]),
            "spearman": stat([r["spearman"] for r in records]), "monotonic": stat([r["monotonic"] for r in records]),
            "within_bounds": stat([r["within_bounds"] for r in records]),
            "preservation": {m: per[m] for m in ("root_dist_m", "timing_corr", "pose_mpjpe_m")},
            "source_matches_prompt": stat([r["source_matches_prompt"] for r in records])}


def summarize(cases: Sequence, records: list[dict], scales: Sequence[float]) -> dict[str, Any]:
    """Group, per-case and re-weighting summaries of the benchmark's records."""
    edits = [r for r in records if r["mode"] != "reweight"]
    weights = [r for r in records if r["mode"] == "reweight"]
    groups = list(dict.fromkeys(c.group for c in cases if c.mode != "reweight"))
    summary = {g: _block([r for r in edits if r["group"] == g]) for g in groups}
    for g, block in summary.items():
        if g.startswith("mirror"):
            e = block["edit"]["success"]
            block["verdict"]["target"] = MIRROR_TARGET
            block["verdict"]["target_met"] = bool(e is not None and e["mean"] >= MIRROR_TARGET)
    per_case = {c.name: _block([r for r in edits if r["case"] == c.name]) for c in cases if c.mode != "reweight"}
    out: dict[str, Any] = {"summary": summary, "per_case": per_case}
    if weights:
        out["reweight"] = {c.name: {"word": c.word, "acting_side": c.acting_side, "amplitude_measure": c.amplitude,
                                    **_reweight_case([r for r in weights if r["case"] == c.name], scales)}
                           for c in cases if c.mode == "reweight"}
        out["reweight_overall"] = {"spearman": stat([r["spearman"] for r in weights]),
                                   "monotonic": stat([r["monotonic"] for r in weights]),
                                   "within_bounds": stat([r["within_bounds"] for r in weights]), "n": len(weights)}
    return out


# ---------------------------------------------------------------- Markdown

def _fmt(s: dict | None, digits: int = 2) -> str:
    if s is None:
        return "-"
    return f"{s['mean']:.{digits}f} ± {s['ci95']:.{digits}f}"


def _digits(metric: str) -> int:
    return 3 if metric.endswith("_m") else 2


def _group_table(summary: dict[str, Any]) -> list[str]:
    metrics = SUCCESS + tuple(m for m, _ in PRESERVATION)
    lines = ["| Group | n | Method | " + " | ".join(_TITLES[m] for m in metrics) + " |",
             "|" + "---|" * (len(metrics) + 3)]
    for g, block in summary.items():
        for method, label in (("edit", "attention edit"), ("baseline", "regenerate target"),
                              ("delta", "Δ edit − baseline")):
            cells = [_fmt(block[method][m], _digits(m)) for m in metrics]
            lines.append(f"| {g} | {block['n']} | {label} | " + " | ".join(cells) + " |")
    return lines


def _verdict_table(summary: dict[str, Any]) -> list[str]:
    lines = ["| Group | Source matches prompt | Success edit / baseline | Preserves more than the baseline? | "
             "Clearly better on |", "|---|---|---|---|---|"]
    for g, block in summary.items():
        v = block["verdict"]
        text = v["text"]
        if "target" in v:
            text += f"; success target ≥ {v['target']:.0%} {'met' if v['target_met'] else 'not met'}"
        lines.append(f"| {g} | {_fmt(block['source_matches_prompt'])} | {_fmt(block['edit']['success'])} / "
                     f"{_fmt(block['baseline']['success'])} | {text} | {', '.join(v['clearly_better_on']) or '-'} |")
    return lines


def _case_table(results: dict[str, Any]) -> list[str]:
    cases = {c["name"]: c for c in results["cases"]}
    lines = ["| Case | Source prompt | Edit | Baseline prompt | Success edit / baseline | "
             "Root dist (m) edit / baseline | Pose MPJPE (m) edit / baseline |", "|---|---|---|---|---|---|---|"]
    for name, block in results["per_case"].items():
        c = cases[name]
        how = c.get("target") or f"mirror {c.get('mirror')}"
        e, b = block["edit"], block["baseline"]
        lines.append(f"| {name} | {c['source']} | {how} | {c['baseline']} | {_fmt(e['success'])} / "
                     f"{_fmt(b['success'])} | {_fmt(e['root_dist_m'], 3)} / {_fmt(b['root_dist_m'], 3)} | "
                     f"{_fmt(e['pose_mpjpe_m'], 3)} / {_fmt(b['pose_mpjpe_m'], 3)} |")
    return lines


def _reweight_table(results: dict[str, Any]) -> list[str]:
    scales = results["settings"]["scales"]
    keys = [_scale_key(s) for s in scales]
    held = results["settings"].get("held", {})
    lines = ["| Case | Word | Held to the source | Amplitude | " + " | ".join(f"s = {k}" for k in keys) +
             " | Plain prompt | Spearman ρ ↑ | Monotonic ↑ |", "|" + "---|" * (len(keys) + 7)]
    for name, r in results["reweight"].items():
        what = f"{r['acting_side']} {r['amplitude_measure'].replace('_', ' ')} (m)"
        lines.append(f"| {name} | {r['word']} | {held.get(name) or '-'} | {what} | " +
                     " | ".join(_fmt(r["amplitude"][k], 3) for k in keys) +
                     f" | {_fmt(r['baseline_amplitude'], 3)} | {_fmt(r['spearman'])} | {_fmt(r['monotonic'])} |")
    for measure, title in (("pose_mpjpe_m", "Lower-body pose MPJPE"), ("root_dist_m", "Root path distance")):
        lines += ["", f"{title} (m) against the source per scale (bound {REWEIGHT_BOUNDS[measure]:.2f} m):", "",
                  "| Case | " + " | ".join(f"s = {k}" for k in keys) + " | Within both bounds at every s ↑ |",
                  "|" + "---|" * (len(keys) + 2)]
        for name, r in results["reweight"].items():
            lines.append(f"| {name} | " + " | ".join(_fmt(r["preservation"][measure][k], 3) for k in keys) +
                         f" | {_fmt(r.get('within_bounds'))} |")
    o = results["reweight_overall"]
    lines += ["", f"All re-weighting cases: Spearman ρ {_fmt(o['spearman'])}, monotonic in s {_fmt(o['monotonic'])}, "
                  f"within the bounds at every s {_fmt(o.get('within_bounds'))} (n = {o['n']} case × seed runs)."]
    return lines


def format_report(results: dict[str, Any]) -> str:
    """The Markdown report: group summary, verdicts, per-case table and the re-weighting table."""
    s, t = results["settings"], results.get("time_s", {})
    lines = ["# Editing benchmark", "",
             f"Model `{s['model']}`, classifier `{s['classifier']}`; suite {s.get('suite', 'tuned')}; seeds "
             f"{s['seeds']}, {s['steps']} {s['sampler']} "
             f"steps{describe_settings(s)}, CFG {s['cfg']:g}; {t.get('edit_calls', '?')} edits and {t.get('baseline_motions', '?')} baseline "
             f"generations in {t.get('total', '?')} s. Values are mean ± 95% CI (1.96·std/√n) over cases × "
             "seeds.", ""]
    if results.get("summary"):
        lines += ["## Success and preservation", ""] + _group_table(results["summary"])
        lines += ["", "## Does attention editing preserve more than regenerating the target?", ""]
        lines += _verdict_table(results["summary"])
        lines += ["", "## Per case", ""] + _case_table(results)
    if results.get("reweight"):
        lines += ["", "## Attention re-weighting", ""] + _reweight_table(results)
    lines += ["", "## Definitions", "",
              "- Success: the edited motion carries the target labels of the content/style/side classifier (mirror: "
              "the side flips left ↔ right against the source) and, where the case has them, every physical sign "
              "agrees (mirror: the other wrist travels further in a wave, rises higher in a raise; walk → run or an "
              "energetic style: faster root; an exhausted or elderly style: slower root; elderly: the trunk leans "
              "further from vertical; an energetic wave: the hand travels further; turn right: negative turning "
              f"angle; a side swap: the new hand rises to within {TARGET_HEIGHT_SLACK:.2f} m of its height in the "
              "regenerated target).",
              "- Baseline: the target prompt (mirror: left and right swapped; re-weighting: the plain prompt) "
              "regenerated from the same noise and length without attention control.",
              "- Label kept: the classifier's style (content edits) or content (style edits) equals the source's.",
              "- Root dist: mean horizontal pelvis distance after aligning the start points; timing corr: "
              "Pearson correlation of the per-frame mean joint speed; pose MPJPE: body-frame joint distance "
              "over the parts that should not change (lower body for arm edits, all joints against the "
              "mirrored source for full mirroring). All against the source (mirror all: the mirrored source).",
              "- Re-weighting amplitude: wrist path length (m, relative to the pelvis) or maximum wrist height above "
              "the pelvis of the named hand; monotonic = never decreasing with s (and not constant). Bounds: at "
              "every s the root path stays within "
              f"{REWEIGHT_BOUNDS['root_dist_m']:.2f} m and the lower body's pose within "
              f"{REWEIGHT_BOUNDS['pose_mpjpe_m']:.2f} m of the source (the cases are standing one-place actions). "
              "Held to the source: the body parts whose latents the edited branch took from the source at every "
              "step (the edit's default, hold=\"auto\": the lower body when a word of a standing action's prompt is "
              "re-weighted)."]
    return "\n".join(lines) + "\n"


def _json_default(x):
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    raise TypeError(f"cannot write {type(x).__name__} to JSON")


def write_results(results: dict[str, Any], out_dir: str | Path) -> Path:
    """results.json and report.md in `out_dir`, each written atomically; returns the report's path."""
    out = Path(out_dir)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2, default=_json_default))
    path = out / "report.md"
    atomic_write_text(path, format_report(results))
    return path
