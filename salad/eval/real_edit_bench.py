"""Benchmark for editing real motions: inversion fidelity, edit success and preservation.

On held-out test clips of a labelled HumanML3D-layout build:

* fidelity: every inversion method samples the clip back under its caption with no
  edit; MPJPE against the input (pelvis-aligned, and global), next to the VAE's own
  reconstruction (the floor), with wall times;
* mirror: left-hand waves mirrored by attention (upper body); success = the motion
  classifier calls the edit a right-side action, preservation = closeness to the
  geometric mirror of the input and the root path;
* style: normal walks swapped to exhausted ("in an ordinary way" -> "in an exhausted
  way"); success = classified exhausted, preservation = the root path.

Both edits are compared with SDEdit (noise the latent to a fraction of T, denoise under
the target prompt) at a few strengths. Writes results.json and report.md.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..data.captions import swap_left_right
from ..data.dataset import read_clip
from ..data.labels import pick_test_clips, read_labels
from ..diffusion.inversion import METHODS, invert
from ..editing.real import decode, edit_inverted, encode, reconstruct
from ..files import atomic_write_text, shown_path
from ..motion.real import load_real_motion
from ..motion.representation import features_to_joints, mirror_features
from .classifiers import load_classifier
from .edit_metrics import mpjpe, root_path_deviation, root_path_error
from .metrics import mean_ci
from .physics import physical_checks
from .sdedit import sdedit

SDEDIT_STRENGTHS = (0.3, 0.5, 0.7)
STYLE_SOURCE = "a person walks forward in an ordinary way"
STYLE_TARGET = "a person walks forward in an exhausted way"

Log = Callable[[str], None]


# ---------------------------------------------------------------- helpers

def _summary(rows: list[dict], keys: Sequence[str]) -> dict:
    out = {"clips": len(rows)}
    for k in keys:
        vals = [r[k] for r in rows if r.get(k) is not None and np.isfinite(r[k])]
        if vals:
            m, ci = mean_ci(vals)
            out[k] = round(m, 5)
            out[f"{k}_ci"] = round(ci, 5)
    return out


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


# ---------------------------------------------------------------- fidelity


def fidelity(pipe, root: Path, names: list[str], methods: Sequence[str], steps: int, cfg: float,
             log: Log = print) -> dict:
    """Inversion + replay with no edit, per method; the VAE's reconstruction as the floor."""

    per_clip = []
    for name in names:
        feats, caption = read_clip(root, name, pipe.canvas_frames)
        real = load_real_motion(feats, pipe.canvas_frames)
        z0 = encode(pipe, real)
        vae = decode(pipe, z0, [caption])[0]
        row = {"clip": name, "frames": real.frames, "prompt": caption,
               "vae": {"mpjpe_m": mpjpe(vae.joints, real.joints),
                       "global_mpjpe_m": mpjpe(vae.joints, real.joints, root_relative=False)}}
        for method in methods:
            inv = invert(pipe, z0, caption, method=method, steps=steps, cfg=cfg)
            rec, replay_s = _timed(lambda: reconstruct(pipe, inv))
            row[method] = {"mpjpe_m": mpjpe(rec.joints, real.joints),
                           "global_mpjpe_m": mpjpe(rec.joints, real.joints, root_relative=False),
                           "latent_error": rec.info["latent_error"],
                           "invert_s": inv.seconds, "replay_s": replay_s, "model_calls": inv.info["model_calls"]}
            log(f"fidelity {name} {method}: MPJPE {100 * row[method]['mpjpe_m']:.2f} cm "
                f"(VAE {100 * row['vae']['mpjpe_m']:.2f} cm), inversion {inv.seconds:.1f} s")
        per_clip.append(row)
    keys = ("mpjpe_m", "global_mpjpe_m", "latent_error", "invert_s", "replay_s", "model_calls")
    summary = {"vae": _summary([r["vae"] for r in per_clip], ("mpjpe_m", "global_mpjpe_m"))}
    for method in methods:
        summary[method] = _summary([r[method] for r in per_clip], keys)
    return {"clips": names, "per_clip": per_clip, "summary": summary}


# ---------------------------------------------------------------- edits


def _judge(clf, variants: dict[str, np.ndarray]) -> dict[str, dict]:
    """Classifier predictions and physical checks for named raw-feature motions."""
    names = list(variants)
    pred = clf.predict([variants[n] for n in names])
    out = {}
    for i, n in enumerate(names):
        row = {h: pred[h][i] for h in clf.classes}
        for h in clf.classes:
            row[f"{h}_probs"] = {c: float(p) for c, p in zip(clf.classes[h], pred[f"{h}_probs"][i])}
        out[n] = row
    return out


def _edit_task(pipe, clf, root: Path, names: list[str], methods: Sequence[str], steps: int, cfg: float,
               strengths: Sequence[float], seed: int, task: str, log: Log, uncorrected: bool = False) -> dict:

    per_clip = []
    for name in names:
        feats, caption = read_clip(root, name, pipe.canvas_frames)
        real = load_real_motion(feats, pipe.canvas_frames)
        z0 = encode(pipe, real)
        if task == "mirror":
            source, target = caption, swap_left_right(caption)
        else:
            source, target = STYLE_SOURCE, STYLE_TARGET
        vae = decode(pipe, z0, [source])[0]
        motions = {"input": real.features, "vae": vae.features}
        seconds = {}
        if task == "mirror":
            motions["geometric mirror"] = mirror_features(real.features)
        recon_err = {}
        for method in methods:
            start = time.perf_counter()
            inv = invert(pipe, z0, source, method=method, steps=steps, cfg=cfg)
            inv_s = time.perf_counter() - start
            for correct in (True, False) if uncorrected else (True,):
                start = time.perf_counter()
                if task == "mirror":
                    res = edit_inverted(pipe, inv, mode="mirror", mirror="upper", correct=correct)
                else:
                    res = edit_inverted(pipe, inv, target, mode="swap", correct=correct)
                key = f"inversion {method}" + ("" if correct else " uncorrected")
                motions[key] = res.edited.features
                seconds[key] = inv_s + time.perf_counter() - start
                recon_err[key] = mpjpe(res.source.joints, real.joints)
        for s in strengths:
            key = f"sdedit {s:g}"
            m, seconds[key] = _timed(lambda: sdedit(pipe, real, target, strength=s, seed=seed, steps=steps, cfg=cfg))
            motions[key] = m.features
        judged = _judge(clf, motions)
        mirror_ref = features_to_joints(motions["geometric mirror"]) if task == "mirror" else None
        for key, f in motions.items():
            j = features_to_joints(f)
            phys = physical_checks(j)
            row = judged[key]
            row.update(seconds=seconds.get(key), root_error_m=root_path_error(j, real.joints),
                       root_error_vs_vae_m=root_path_error(j, vae.joints),
                       root_path_deviation_m=root_path_deviation(j, real.joints),
                       foot_skating_ratio=phys["foot_skating_ratio"], acceleration_mps2=phys["acceleration_mps2"],
                       mpjpe_to_input_m=mpjpe(j, real.joints),
                       root_speed_mps=phys["root_speed_mps"],
                       wrist_path_right_over_left=phys["right_wrist_path_m"] / max(phys["left_wrist_path_m"], 1e-6))
            if key in recon_err:
                row["source_branch_mpjpe_m"] = recon_err[key]
            if task == "mirror":
                row["success"] = float(row["side"] == "right")
                row["mpjpe_to_mirror_m"] = mpjpe(j, mirror_ref)
                row["p_right"] = row["side_probs"]["right"]
            else:
                row["success"] = float(row["style"] == "exhausted")
                row["p_exhausted"] = row["style_probs"]["exhausted"]
                row["content_kept"] = float(row["content"] == "walk")
        per_clip.append({"clip": name, "frames": real.frames, "source_prompt": source, "target_prompt": target,
                         "variants": judged})
        brief = ", ".join(f"{k}: {judged[k]['side' if task == 'mirror' else 'style']}" for k in judged)
        log(f"{task} {name}: {brief}")
    keys = ["success", "root_error_m", "root_error_vs_vae_m", "root_path_deviation_m", "mpjpe_to_input_m",
            "root_speed_mps", "wrist_path_right_over_left", "foot_skating_ratio", "acceleration_mps2", "seconds",
            "source_branch_mpjpe_m"]
    keys += ["p_right", "mpjpe_to_mirror_m"] if task == "mirror" else ["p_exhausted", "content_kept"]
    variants = list(per_clip[0]["variants"]) if per_clip else []
    summary = {v: _summary([c["variants"][v] for c in per_clip], keys) for v in variants}
    return {"clips": names, "per_clip": per_clip, "summary": summary}


# ---------------------------------------------------------------- the whole benchmark


def run_real_edit_bench(pipe, data: str | Path, classifier: str | Path, out: str | Path,
                        clips: int = 10, edit_clips: int = 8, methods: Sequence[str] | None = None,
                        edit_methods: Sequence[str] = ("negative", "fixed_point"), steps: int = 50,
                        cfg: float = 7.5, strengths: Sequence[float] = SDEDIT_STRENGTHS, seed: int = 0,
                        uncorrected: bool = False, log: Log = print) -> dict:
    """Run the three parts and write results.json and report.md into `out`. uncorrected=True
    also runs each edit without the per-step corrections."""

    root = Path(data)
    if not (root / "new_joint_vecs").is_dir():
        raise FileNotFoundError(f"{root}: not a HumanML3D-layout dataset (no new_joint_vecs/)")
    methods = list(METHODS if methods is None else methods)
    for m in list(methods) + list(edit_methods):
        if m not in METHODS:
            raise ValueError(f"unknown inversion method {m!r}; choose from {', '.join(METHODS)}")
    if clips < 0 or edit_clips < 0:
        raise ValueError("clip counts must not be negative")
    labels = read_labels(root)
    clf = load_classifier(classifier)
    t0 = time.perf_counter()
    results = {"config": {"data": str(root), "classifier": shown_path(classifier), "model": shown_path(pipe.source),
                          "steps": steps,
                          "cfg": cfg, "methods": methods, "edit_methods": list(edit_methods),
                          "sdedit_strengths": list(strengths), "seed": seed, "uncorrected": uncorrected}}
    if clips:
        results["fidelity"] = fidelity(pipe, root, pick_test_clips(labels, clips), methods, steps, cfg, log)
    if edit_clips:
        waves = pick_test_clips(labels, edit_clips, content="wave-left-hand")
        results["mirror"] = _edit_task(pipe, clf, root, waves, edit_methods, steps, cfg, strengths, seed, "mirror",
                                       log, uncorrected)
        walks = pick_test_clips(labels, edit_clips, content="walk", style="normal")
        results["style"] = _edit_task(pipe, clf, root, walks, edit_methods, steps, cfg, strengths, seed, "style", log,
                                      uncorrected)
    results["wall_seconds"] = round(time.perf_counter() - t0, 1)
    write_real_edit_report(results, out)
    return results


def _pm(s: dict, k: str, scale: float = 1.0, fmt: str = "{:.2f}") -> str:
    if k not in s:
        return "–"
    return f"{fmt.format(scale * s[k])} ± {fmt.format(scale * s[k + '_ci'])}"


def write_real_edit_report(results: dict, out: str | Path) -> Path:
    out = Path(out)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2, default=float))
    c = results["config"]
    lines = ["# Editing real motions: inversion and attention edits", "",
             f"Model `{c['model']}`, data `{c['data']}` (test split), {c['steps']} DDIM steps, cfg {c['cfg']}. "
             "Values are mean ± 1.96·std/√clips.", ""]
    if "fidelity" in results:
        f = results["fidelity"]
        lines += ["## Inversion fidelity (no edit, source caption)", "",
                  f"{len(f['clips'])} clips. MPJPE with the pelvis aligned (cm), global MPJPE (cm, includes root "
                  "drift), inversion and replay wall time (s), denoiser calls per inversion.", "",
                  "| method | MPJPE cm | global MPJPE cm | inversion s | replay s | model calls |",
                  "| --- | --- | --- | --- | --- | --- |"]
        s = f["summary"]
        lines.append(f"| VAE only (floor) | {_pm(s['vae'], 'mpjpe_m', 100)} | {_pm(s['vae'], 'global_mpjpe_m', 100)} "
                     "| – | – | – |")
        for m in c["methods"]:
            r = s[m]
            lines.append(f"| {m} | {_pm(r, 'mpjpe_m', 100)} | {_pm(r, 'global_mpjpe_m', 100)} | {_pm(r, 'invert_s')} "
                         f"| {_pm(r, 'replay_s')} | {r.get('model_calls', 0):.0f} |")
        lines.append("")
    # (column title, summary key, scale, format) per table; the first table is what the edit did, the second
    # what it kept and what it cost
    effect = {"mirror": [("p(right)", "p_right", 1, "{:.2f}"), ("MPJPE to geometric mirror cm", "mpjpe_to_mirror_m", 100,
                                                                 "{:.2f}"),
                         ("wrist path R/L", "wrist_path_right_over_left", 1, "{:.2f}")],
              "style": [("p(exhausted)", "p_exhausted", 1, "{:.2f}"), ("walk kept", "content_kept", 1, "{:.2f}"),
                        ("root speed m/s", "root_speed_mps", 1, "{:.2f}")]}
    kept = [("root err cm", "root_error_m", 100, "{:.1f}"), ("root err vs VAE cm", "root_error_vs_vae_m", 100, "{:.1f}"),
            ("path deviation cm", "root_path_deviation_m", 100, "{:.1f}"),
            ("foot skating", "foot_skating_ratio", 1, "{:.3f}"), ("accel m/s²", "acceleration_mps2", 1, "{:.2f}"),
            ("source branch MPJPE cm", "source_branch_mpjpe_m", 100, "{:.2f}"), ("s / edit", "seconds", 1, "{:.1f}")]
    titles = {"mirror": "Mirror a left-hand wave (mode mirror, upper body)",
              "style": f"Style swap: “{STYLE_SOURCE}” → “{STYLE_TARGET}”"}
    goals = {"mirror": "classified right-side", "style": "classified exhausted"}
    for task in ("mirror", "style"):
        if task not in results:
            continue
        r = results[task]
        lines += [f"## {titles[task]}", "", f"{len(r['clips'])} test clips. success = {goals[task]}; MPJPE with the "
                  "pelvis aligned; root errors frame by frame; path deviation = distance of each root position to "
                  "the input's path, whatever the speed along it.", ""]
        for cols in ([("success", "success", 1, "{:.2f}"), ("MPJPE to input cm", "mpjpe_to_input_m", 100, "{:.2f}")]
                     + effect[task], kept):
            lines += ["| variant | " + " | ".join(c[0] for c in cols) + " |", "|" + " --- |" * (len(cols) + 1)]
            for v, s in r["summary"].items():
                lines.append(f"| {v} | " + " | ".join(_pm(s, k, sc, f) for _, k, sc, f in cols) + " |")
            lines.append("")
    lines += [f"Wall time: {results.get('wall_seconds', 0):.0f} s.", ""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path
