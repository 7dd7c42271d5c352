"""`salad eval-edit`: the zero-shot editing benchmark.

For every case of the prompt suite (salad.eval.edit_suite) and every seed, the model makes one edit with
`Pipeline.edit` (source and edited branch from the same noise) and, as the naive baseline, regenerates the
baseline prompt from the same noise and length with no attention control. The real content/style/side
classifier and the physical checks then judge each output against the source:

* success: the edit reached its target (classifier labels, and a physical sign where the case has one);
* preservation: label kept, root path distance, timing correlation and pose distance of the parts that
  should not change (salad.eval.edit_metrics);
* reweight: the acting hand's amplitude for each scale s, its Spearman correlation with s and whether it
  is monotonic.

Results are mean ± 95% CI over cases × seeds, written as results.json and report.md.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Sequence

import numpy as np

from ..files import shown_path
from .edit_suite import AMPLITUDES, DEFAULT_SCALES, REWEIGHT_BOUNDS, TARGET_HEIGHT_SLACK, EditCase, default_suite

CHECK_KEYS = ("left_wrist_path_m", "right_wrist_path_m", "left_wrist_height_m", "right_wrist_height_m",
              "root_speed_mps", "turn_deg", "trunk_lean_deg")
HEADS = ("content", "style", "side")
BASELINE_BATCH = 16


# ---------------------------------------------------------------- generation

def regenerate(pipe, prompts: Sequence[str], seeds: Sequence[int], frames: int, steps: int = 50,
               cfg: float = 7.5, sampler: str = "ddim") -> list:
    """Plain generations in one batched run, row i from exactly the noise `pipe.generate(prompts[i],
    seed=seeds[i])` starts from (generate_batch shares one seed across rows, so it cannot pair them)."""
    import torch

    if len(prompts) != len(seeds) or not prompts:
        raise ValueError("give one seed per prompt")
    prompts = [pipe.check_prompt(p) for p in prompts]
    steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler)
    noise = torch.cat([pipe.noise(1, frames, int(s)) for s in seeds])
    text = pipe.sampler_text(list(prompts), sampler)
    z = pipe.denoise(text, noise, sampler, steps, cfg, auto=False, seed=[int(s) for s in seeds])
    motions = pipe.decode(z, frames, list(prompts), int(seeds[0]))
    for m, s in zip(motions, seeds):
        m.seed = int(s)
    return motions


def _check_classifier(classifier, cases: Sequence[EditCase], where: str) -> None:
    missing = [h for h in HEADS if h not in classifier.classes]
    if missing:
        raise ValueError(f"{where}: the classifier has no {', '.join(missing)} head(s); the benchmark needs "
                         f"content, style and side")
    for case in cases:
        for head, labels in case.required_labels().items():
            lacking = sorted(labels - set(classifier.classes[head]))
            if lacking:
                raise ValueError(f"{where}: case {case.name!r} needs {head} class(es) {', '.join(lacking)}, "
                                 f"which the classifier does not know")


def _check_settings(seeds: int, scales: Sequence[float]) -> tuple[float, ...]:
    if not isinstance(seeds, (int, np.integer)) or seeds < 1:
        raise ValueError(f"seeds must be a positive integer, got {seeds!r}")
    scales = tuple(float(s) for s in scales)
    if len(set(scales)) < 2 or any(not -3.0 <= s <= 3.0 for s in scales):
        raise ValueError(f"reweight scales must be at least 2 distinct values in [-3, 3], got {scales}")
    return tuple(sorted(scales))


# ---------------------------------------------------------------- judging one output

def _describe(labels: dict[str, str], checks: dict[str, float]) -> dict[str, Any]:
    return {**{h: labels[h] for h in HEADS}, "checks": {k: round(checks[k], 4) for k in CHECK_KEYS}}


def _physical_sign(kind: str, case: EditCase, source: dict, out: dict, target: dict | None) -> bool:
    from .edit_metrics import dominant_wrist, other_side
    s, o = source["checks"], out["checks"]
    if kind == "faster":
        return o["root_speed_mps"] > s["root_speed_mps"]
    if kind == "slower":
        return o["root_speed_mps"] < s["root_speed_mps"]
    if kind == "turn_left":
        return o["turn_deg"] > 0
    if kind == "turn_right":
        return o["turn_deg"] < 0
    if kind == "leans_forward":
        return o["trunk_lean_deg"] > s["trunk_lean_deg"]
    key = AMPLITUDES[case.amplitude]
    if kind == "wrist_flip":
        # the case's own amplitude: travel for a wave, height for a raise (a raised arm hardly travels)
        before = dominant_wrist(s[key.format(side="left")], s[key.format(side="right")])
        return dominant_wrist(o[key.format(side="left")], o[key.format(side="right")]) == other_side(before)
    acting = key.format(side=case.acting_side)
    if kind == "livelier":
        return o[acting] > s[acting]
    if kind == "reaches_target_height":
        if target is None:
            raise ValueError(f"case {case.name!r}: the target-height check needs the regenerated target")
        return o[acting] >= target["checks"][acting] - TARGET_HEIGHT_SLACK
    raise ValueError(f"unknown physical check {kind!r}")


def _physics_ok(case: EditCase, source: dict, out: dict, target: dict | None = None) -> bool | None:
    """All of the case's directional checks (None when it has none)."""
    if not case.physics:
        return None
    return all(_physical_sign(kind, case, source, out, target) for kind in case.physics)


def judge(case: EditCase, source: dict, out: dict, joints: np.ndarray, reference: np.ndarray,
          target: dict | None = None) -> dict[str, Any]:
    """Success and preservation of one output (edit or baseline) against its source; `target`: the
    regenerated target prompt's description, for checks that compare with it."""
    from .edit_metrics import pose_distance, root_trajectory_distance, side_flipped, timing_correlation
    hits = []
    for head, want in case.expect.items():
        hits.append(side_flipped(source[head], out[head]) if want == "flip" else out[head] == want)
    classifier_ok = all(hits)
    physics_ok = _physics_ok(case, source, out, target)
    return {
        **{h: out[h] for h in HEADS}, "checks": out["checks"],
        "classifier_ok": classifier_ok, "physics_ok": physics_ok,
        "success": classifier_ok and physics_ok is not False,
        "label_kept": None if case.keep is None else out[case.keep] == source[case.keep],
        "root_dist_m": root_trajectory_distance(joints, reference),
        "timing_corr": timing_correlation(joints, reference),
        "pose_mpjpe_m": None if case.pose_joints is None else pose_distance(joints, reference, case.pose_joints),
    }


def _matches_prompt(case: EditCase, source: dict) -> bool:
    return all(source[h] == want for h, want in case.source_expect.items())


def _amplitude(case: EditCase, described: dict) -> float:
    return float(described["checks"][AMPLITUDES[case.amplitude].format(side=case.acting_side)])


# ---------------------------------------------------------------- the benchmark

def _make_edits(pipe, cases: Sequence[EditCase], seeds: list[int], frames_of: dict[str, int],
                scales: tuple[float, ...], sampling: dict, say: Callable[[str], None]) -> dict[tuple, Any]:
    """{(case, seed) or (case, seed, scale): EditResult}, one Pipeline.edit call each."""
    from ..motion.representation import FPS
    t0 = time.time()
    edits: dict[tuple, Any] = {}
    for i, case in enumerate(cases):
        kw = dict(seconds=frames_of[case.name] / FPS, **sampling)
        for seed in seeds:
            if case.mode == "reweight":
                for s in scales:
                    edits[case.name, seed, s] = pipe.edit(case.source, mode="reweight", reweight={case.word: s},
                                                          seed=seed, **kw)
            elif case.mode == "mirror":
                edits[case.name, seed] = pipe.edit(case.source, mode="mirror", mirror=case.mirror, seed=seed, **kw)
            else:
                edits[case.name, seed] = pipe.edit(case.source, case.target, mode=case.mode, seed=seed, **kw)
        say(f"[{i + 1}/{len(cases)}] {case.mode}: {case.name} ({len(seeds)} seeds, {time.time() - t0:.0f} s)")
    return edits


def _make_baselines(pipe, cases: Sequence[EditCase], seeds: list[int], frames_of: dict[str, int],
                    sampling: dict) -> dict[tuple, Any]:
    """{(baseline prompt, seed, frames): Motion}, each distinct one generated once, in batches."""
    wanted = sorted({(c.baseline, seed, frames_of[c.name]) for c in cases for seed in seeds},
                    key=lambda k: (k[2], k[0], k[1]))
    out: dict[tuple, Any] = {}
    for n in sorted({k[2] for k in wanted}):
        rows = [k for k in wanted if k[2] == n]
        for s in range(0, len(rows), BASELINE_BATCH):
            chunk = rows[s:s + BASELINE_BATCH]
            out.update(zip(chunk, regenerate(pipe, [k[0] for k in chunk], [k[1] for k in chunk], n, **sampling)))
    return out


def _describe_all(classifier, motions: dict[tuple, Any]) -> dict[tuple, dict]:
    """Classifier labels (one batched call) and physical checks of every motion."""
    from .physics import physical_checks
    keys = list(motions)
    pred = classifier.predict([motions[k].features for k in keys])
    return {k: _describe({h: pred[h][i] for h in HEADS}, physical_checks(motions[k].joints))
            for i, k in enumerate(keys)}


def _record(case: EditCase, seed: int, frames: int, motions: dict, described: dict,
            scales: tuple[float, ...]) -> dict[str, Any]:
    from ..motion.representation import mirror_joints
    from .edit_metrics import is_monotonic, spearman
    src_key = ("source", case.name, seed)
    src, src_joints = described[src_key], motions[src_key].joints
    base_key = ("baseline", case.baseline, seed, frames)
    rec: dict[str, Any] = {"case": case.name, "mode": case.mode, "group": case.group, "seed": seed, "frames": frames,
                           "source": src, "source_matches_prompt": _matches_prompt(case, src)}
    reference = mirror_joints(src_joints) if case.reference == "mirrored" else src_joints
    if case.mode != "reweight":
        edit_key = ("edit", case.name, seed)
        target = described[base_key]
        rec["edit"] = judge(case, src, described[edit_key], motions[edit_key].joints, reference, target)
        rec["baseline"] = judge(case, src, target, motions[base_key].joints, reference, target)
        return rec
    keys = [("edit", case.name, seed, s) for s in scales]
    judged = [judge(case, src, described[k], motions[k].joints, reference) for k in keys]
    amps = [_amplitude(case, described[k]) for k in keys]
    rec.update(scales=list(scales), amplitude=amps, source_amplitude=_amplitude(case, src),
               baseline_amplitude=_amplitude(case, described[base_key]),
               spearman=spearman(scales, amps), monotonic=is_monotonic(amps),
               content=[described[k]["content"] for k in keys],
               **{m: [j[m] for j in judged] for m in ("root_dist_m", "timing_corr", "pose_mpjpe_m")})
    rec["within_bounds"] = all(v is None or v <= bound for m, bound in REWEIGHT_BOUNDS.items() for v in rec[m])
    return rec


def run_edit_benchmark(pipe, classifier, cases: Sequence[EditCase] | None = None, seeds: int = 3,
                       steps: int = 50, cfg: float = 7.5, sampler: str = "ddim",
                       scales: Sequence[float] = DEFAULT_SCALES, seed_base: int = 0,
                       progress: Callable[[str], None] | None = None, suite: str = "tuned") -> dict[str, Any]:
    """Run every case (default: all of `suite`'s) for `seeds` seeds (seed_base, seed_base + 1, ...) and
    return the settings, the raw records per (case, seed) and their summaries (layout in
    salad.eval.edit_report)."""
    from .edit_report import summarize

    cases = list(default_suite(suite=suite) if cases is None else cases)
    if not cases:
        raise ValueError("no cases to run")
    scales = _check_settings(seeds, scales)
    _check_classifier(classifier, cases, "eval-edit")
    steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler)
    sampling = dict(steps=steps, cfg=cfg, sampler=sampler)
    seed_list = [seed_base + k for k in range(seeds)]
    say = progress or (lambda msg: None)
    # one fixed length per case, so that source, edit and baseline line up frame by frame
    frames_of = {c.name: pipe.frames_for(min(c.seconds, pipe.max_seconds)) for c in cases}

    t0 = time.time()
    edits = _make_edits(pipe, cases, seed_list, frames_of, scales, sampling, say)
    t1 = time.time()
    baselines = _make_baselines(pipe, cases, seed_list, frames_of, sampling)
    t2 = time.time()
    say(f"baselines: {len(baselines)} plain generations ({t2 - t1:.0f} s)")

    motions: dict[tuple, Any] = {}
    for key, res in edits.items():
        motions[("source",) + key[:2]] = res.source      # re-weighting shares one source over its scales
        motions[("edit",) + key] = res.edited
    motions.update({("baseline",) + key: m for key, m in baselines.items()})
    described = _describe_all(classifier, motions)
    records = [_record(c, seed, frames_of[c.name], motions, described, scales) for c in cases for seed in seed_list]

    settings = {"model": shown_path(getattr(pipe, "source", "")),
                "classifier": shown_path(getattr(classifier, "meta", {}).get("path", "")),
                "suite": suite, "seeds": seed_list, **sampling, **pipe.sampler_settings(sampler), "scales": list(scales),
                "frames": frames_of,
                "edit_defaults": _edit_defaults(edits), "held": _held_parts(edits)}
    results = {"settings": settings, "cases": [_case_dict(c) for c in cases], "records": records}
    results.update(summarize(cases, records, scales))
    results["time_s"] = {"edits": round(t1 - t0, 1), "baselines": round(t2 - t1, 1),
                         "total": round(time.time() - t0, 1), "edit_calls": len(edits),
                         "baseline_motions": len(baselines)}
    return results


def _edit_defaults(edits: dict) -> dict[str, Any]:
    """tau / self-injection the pipeline used per mode (its defaults), as recorded in EditResult.params."""
    out: dict[str, Any] = {}
    for res in edits.values():
        p = res.params
        out.setdefault(p["mode"], {"tau": p.get("tau"), "self_inject": p.get("self_inject")})
    return out


def _held_parts(edits: dict) -> dict[str, str | None]:
    """The body parts each case's edits held to the source (Pipeline.resolve_hold; "mixed" if they differ)."""
    out: dict[str, str | None] = {}
    for key, res in edits.items():
        hold = res.params.get("hold")
        out[key[0]] = hold if out.get(key[0], hold) == hold else "mixed"
    return out


def _case_dict(case: EditCase) -> dict[str, Any]:
    from dataclasses import asdict
    d = asdict(case)
    d["baseline"] = case.baseline
    return {k: v for k, v in d.items() if v not in (None, {}, "")}
