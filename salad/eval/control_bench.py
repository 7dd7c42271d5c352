"""`salad eval-control`: how well guided generation follows real trajectories, and what it costs in realism.

Protocol (MoLA §4.2 / Table 2, which follows MotionLCM and OmniControl): each of `samples` test motions,
cut to at most `max_frames` frames (a multiple of 4), gives one of its captions and a control signal: the
positions of the controlled joints (the pelvis by default) in the motion's own global frame, at every frame
("100%") or at a random subset of frames (OmniControl's density: "1", "2", "5" frames or "25%" of them).
The model generates the caption under that control, and, as the reference, without control from the same
noise and length.

Control errors, with e_ik = ||p_ik - q_ik||_2 in metres between the generated and the real position of the
k-th controlled (frame, joint) of motion i (OmniControl's `calculate_trajectory_error`, strict mode, as used
by MotionLCM's ControlMetrics):

* Traj. err (θ): share of motions whose trajectory fails, i.e. with max_k e_ik > θ;
* Loc. err (θ): mean over motions of the share of their controlled locations with e_ik > θ;
* Avg. err: mean over motions of mean_k e_ik;

for θ = 50 cm (the numbers MoLA reports) and 20 cm.

Realism, with the T2M evaluator: FID of the generated motions against all real motions of the split (their first
`max_frames` frames, as in `salad eval`), R-precision top-1/2/3 within consecutive pools of min(32, samples)
motions, MM-Dist, Diversity and the foot skating ratio (salad.eval.physics). The same numbers for the real
windows and for the unconstrained generations put them in context (target: controlled R-precision at least
0.9 x unconstrained).

AITS: wall time of one guided generation (batch 1: guided DDIM with CFG, refinement, VAE decode) averaged over the
samples, on the pipeline's device (this machine's CPU threads unless a GPU is used); MoLA reports 1.04 s on an
A100 GPU.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..diffusion.sampling import describe_settings
from ..files import atomic_write_text
from ..motion import skeleton as sk
from ..motion.control import ControlSignal, control_errors, make_signal
from ..motion.representation import FPS, features_to_joints
from .metrics import diversity, frechet_distance, gaussian_stats, matching_distance, r_precision
from .physics import foot_skating_ratio
from .sampling import fixed_crop

THRESHOLDS_M = (0.5, 0.2)
MAX_POOL = 32
# OmniControl's controllable joints; any joint name of the skeleton is accepted
OMNICONTROL_JOINTS = ("pelvis", "left_foot", "right_foot", "head", "left_wrist", "right_wrist")
MOLA_TABLE2 = {"method": "MoLA (paper, HumanML3D, A100)", "R_precision_top3": 0.761, "FID": 0.486,
               "Diversity": 9.322, "Traj_err_50cm": 0.271, "Loc_err_50cm": 0.051, "Avg_err_m": 0.159, "AITS_s": 1.04}


@dataclass
class ControlCase:
    name: str
    caption: str
    features: np.ndarray        # (frames, 263) the real window
    signal: ControlSignal

    @property
    def frames(self) -> int:
        return len(self.features)


# ---------------------------------------------------------------- cases

def parse_joints(text: str | Sequence[str]) -> list[int]:
    """'pelvis,left_wrist' (names or indices) -> joint indices."""
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text) if str(t).strip()]
    if not items:
        raise ValueError("no joints to control")
    out = []
    for t in items:
        if str(t).isdigit() and int(t) < sk.NUM_JOINTS:
            out.append(int(t))
        elif t in sk.JOINT_NAMES:
            out.append(sk.JOINT_NAMES.index(t))
        else:
            raise ValueError(f"unknown joint {t!r}; use names such as {', '.join(OMNICONTROL_JOINTS)}")
    return sorted(set(out))


def parse_density(text: str | int | float) -> tuple[str, float]:
    """OmniControl's density: '100%' / '25%' (share of frames) or '1', '2', '5' (number of frames)."""
    s = str(text).strip()
    try:
        if s.endswith("%"):
            v = float(s[:-1])
            if not 0 < v <= 100:
                raise ValueError
            return "percent", v
        v = int(s)
        if v < 1:
            raise ValueError
        return "frames", float(v)
    except ValueError:
        raise ValueError(f"density must be a percentage in (0, 100] such as '25%' or a frame count such as '5', "
                         f"got {text!r}") from None


def controlled_frames(frames: int, density: tuple[str, float], rng: np.random.Generator) -> np.ndarray:
    """Sorted frame indices under control: all of them at 100%, else a random subset."""
    kind, v = density
    n = int(frames * v / 100) if kind == "percent" else int(v)
    n = min(max(n, 1), frames)
    if n == frames:
        return np.arange(frames)
    return np.sort(rng.choice(frames, n, replace=False))


def make_cases(dataset, samples: int, joints: Sequence[int] = (0,), density: str = "100%", seed: int = 0,
               max_frames: int = 196) -> list[ControlCase]:
    """`samples` test motions drawn at random (fixed by `seed`), each with one caption and its control signal."""
    if samples < 1:
        raise ValueError(f"samples must be at least 1, got {samples}")
    dens = parse_density(density)
    joints = list(joints)
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(dataset.items))
    cases = []
    for i in order:
        item = dataset.items[i]
        n = (min(len(item.features), max_frames) // 4) * 4
        if n < 16:
            continue
        f = item.features[:n].astype(np.float32)
        pos = features_to_joints(f).astype(np.float64)
        mask = np.zeros((n, sk.NUM_JOINTS), dtype=bool)
        mask[np.ix_(controlled_frames(n, dens, rng), joints)] = True
        caption = item.captions[int(rng.integers(len(item.captions)))]
        cases.append(ControlCase(item.name, caption, f, make_signal(pos, mask)))
        if len(cases) == samples:
            break
    if not cases:
        raise ValueError(f"{dataset.root}: no motion of at least 16 frames to control")
    return cases


# ---------------------------------------------------------------- metrics

def control_error_metrics(errors: Sequence[np.ndarray], thresholds: Sequence[float] = THRESHOLDS_M) -> dict[str, float]:
    """Traj. err, Loc. err (per threshold) and Avg. err from each motion's controlled-location errors (m)."""
    errs = [np.asarray(e, dtype=np.float64) for e in errors]
    if not errs or any(e.size == 0 for e in errs):
        raise ValueError("every motion needs at least one controlled location")
    out: dict[str, float] = {}
    for th in thresholds:
        cm = f"{round(th * 100):d}cm"
        out[f"Traj_err_{cm}"] = float(np.mean([(e > th).any() for e in errs]))
        out[f"Loc_err_{cm}"] = float(np.mean([(e > th).mean() for e in errs]))
    per = np.array([e.mean() for e in errs])
    out["Avg_err_m"] = float(per.mean())
    out["Avg_err_ci95_m"] = float(1.96 * per.std(ddof=1) / np.sqrt(len(per))) if len(per) > 1 else 0.0
    out["Max_err_m"] = float(np.mean([e.max() for e in errs]))
    return out


def realism_metrics(evaluator, features: Sequence[np.ndarray], text_emb: np.ndarray,
                    reference: tuple[np.ndarray, np.ndarray], pool: int, seed: int = 0) -> dict[str, float]:
    m_emb = evaluator.embed_motions(list(features))
    top = r_precision(text_emb, m_emb, pool=pool)
    out = {f"R_precision_top{k + 1}": float(top[k]) for k in range(3)}
    out["FID"] = frechet_distance(*gaussian_stats(m_emb), *reference)
    out["MM_Dist"] = matching_distance(text_emb, m_emb)
    out["Diversity"] = diversity(m_emb, 300, np.random.default_rng(seed))
    out["Foot_skating"] = float(np.mean([foot_skating_ratio(features_to_joints(f)) for f in features]))
    return out


# ---------------------------------------------------------------- the benchmark

SETTING_KEYS = ("strength", "gradient_steps", "refine_steps", "repeats")


def _setting_name(s: dict) -> str:
    parts = [f"strength {s.get('strength', 1.0):g}"]
    for key, label in (("gradient_steps", "grad steps"), ("refine_steps", "refine steps"), ("repeats", "repeats")):
        if s.get(key) is not None:
            parts.append(f"{label} {s[key]}")
    return "Controlled (" + ", ".join(parts) + ")"


def evaluate_control(pipe, dataset, evaluator, samples: int = 32, steps: int | None = None, cfg: float = 7.5,
                     sampler: str = "ddim", settings: Sequence[dict] = ({"strength": 1.0},), joints: Sequence[int] = (0,),
                     density: str = "100%", seed: int = 0, max_frames: int = 196,
                     progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the protocol on `dataset` (a MotionDataset; its items are the test motions) for each guidance
    setting: a dict with keys among SETTING_KEYS, passed to Pipeline.control. sampler: "ddim" or
    "consistency" (the distilled student), for the unconstrained and the controlled rows alike."""
    import torch

    steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler)

    settings = [dict(s) for s in settings]
    for s in settings:
        unknown = set(s) - set(SETTING_KEYS)
        if unknown:
            raise ValueError(f"unknown guidance setting(s) {sorted(unknown)}")
    if not settings:
        raise ValueError("give at least one guidance setting")
    t_start = time.time()
    cases = make_cases(dataset, samples, joints, density, seed, min(max_frames, pipe.canvas_frames))
    if len(cases) < 2:
        raise ValueError(f"{dataset.root}: FID and R-precision need at least 2 motions, found {len(cases)}")
    pool = min(MAX_POOL, len(cases))
    reference = gaussian_stats(evaluator.embed_motions([fixed_crop(it.features, max_frames) for it in dataset.items]))
    captions = [c.caption for c in cases]
    text_emb = evaluator.embed_texts(captions)
    say = progress or (lambda msg: None)

    rows: dict[str, dict[str, Any]] = {}
    real = realism_metrics(evaluator, [c.features for c in cases], text_emb, reference, pool, seed)
    rows["Real motion"] = {"realism": real}

    def run(name: str, generate: Callable[[int, ControlCase], Any]) -> None:
        feats, errors, times, per = [], [], [], []
        for k, case in enumerate(cases):
            t0 = time.perf_counter()
            m = generate(k, case)
            times.append(time.perf_counter() - t0)
            e = control_errors(m.joints, case.signal)
            feats.append(m.features)
            errors.append(e)
            per.append({"name": case.name, "avg_err_m": float(e.mean()), "max_err_m": float(e.max()),
                        "seconds": round(times[-1], 3)})
            say(f"{name} [{k + 1}/{len(cases)}] {case.name}: avg err {e.mean():.3f} m, max {e.max():.3f} m "
                f"({times[-1]:.1f} s)")
        rows[name] = {"control": control_error_metrics(errors),
                      "realism": realism_metrics(evaluator, feats, text_emb, reference, pool, seed),
                      "AITS_s": float(np.mean(times)), "per_sample": per}

    def seed_of(k: int) -> int:
        return seed * 100003 + k

    run("Unconstrained", lambda k, c: pipe.generate(c.caption, seconds=c.frames / FPS, seed=seed_of(k), steps=steps,
                                                    cfg=cfg, sampler=sampler))
    for s in settings:
        run(_setting_name(s), lambda k, c, s=s: pipe.control(c.caption, signal=c.signal, seed=seed_of(k), steps=steps,
                                                             cfg=cfg, sampler=sampler, **s))
        rows[_setting_name(s)]["setting"] = s
    free = rows["Unconstrained"]["realism"]
    for name, r in rows.items():
        if name.startswith("Controlled"):
            r["R_precision_vs_unconstrained"] = {
                f"top{k}": (r["realism"][f"R_precision_top{k}"] / free[f"R_precision_top{k}"]
                            if free[f"R_precision_top{k}"] > 0 else float("nan")) for k in (1, 2, 3)}
    return {
        "rows": rows,
        "protocol": {"dataset": str(dataset.root), "samples": len(cases), "pool": pool, "steps": steps, "cfg": cfg,
                     "sampler": sampler, "unconstrained_sampling": pipe.sampler_settings(sampler),
                     "joints": [sk.JOINT_NAMES[j] for j in joints], "density": str(density), "seed": seed,
                     "max_frames": max_frames, "reference_motions": len(dataset.items),
                     "torch_threads": torch.get_num_threads(), "device": str(pipe.device),
                     "thresholds_m": list(THRESHOLDS_M)},
        "cases": [{"name": c.name, "caption": c.caption, "frames": c.frames,
                   "controlled_locations": int(c.signal.joint_mask().sum())} for c in cases],
        "paper": MOLA_TABLE2,
        "time_s": round(time.time() - t_start, 1),
    }


# ---------------------------------------------------------------- report

_CONTROL_COLS = ("Traj_err_50cm", "Loc_err_50cm", "Traj_err_20cm", "Loc_err_20cm", "Avg_err_m")
_REAL_COLS = ("R_precision_top1", "R_precision_top2", "R_precision_top3", "FID", "MM_Dist", "Diversity", "Foot_skating")


def _where(protocol: dict) -> str:
    device = protocol.get("device", "cpu")       # results written before the device was recorded ran on the CPU
    return f"{protocol['torch_threads']} CPU thread(s)" if device == "cpu" else f"the {device} GPU"


def _unconstrained_sampling(protocol: dict) -> str:
    """How the Unconstrained row sampled where that differs from the guided rows (reports written before it was
    recorded say nothing)."""
    settings = protocol.get("unconstrained_sampling")
    sampler = protocol.get("sampler", "ddim")
    if not settings or sampler == "consistency":
        return ""
    words = describe_settings({**settings, "sampler": sampler})
    skipped = "".join(f" and {w}" for w, key in (("unprojected", "projections"),
                                                  ("without the feet refinement", "foot_refine")) if settings.get(key))
    return f"; the Unconstrained row{words}, the guided rows deterministic with guidance at every step{skipped}"


def markdown_report(results: dict[str, Any]) -> str:
    p = results["protocol"]
    head = ["Method", *[c.replace("_", " ") for c in _CONTROL_COLS], *[c.replace("_", " ") for c in _REAL_COLS],
            "AITS (s)"]
    lines = ["# Guided control: path following", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results["rows"].items():
        ctl, real = r.get("control", {}), r.get("realism", {})
        cells = [name]
        for c in _CONTROL_COLS:
            v = ctl.get(c)
            if v is None:
                cells.append("-")
            else:
                cells.append(f"{v:.3f} ± {ctl['Avg_err_ci95_m']:.3f}" if c == "Avg_err_m" else f"{v:.3f}")
        cells += ["-" if real.get(c) is None else f"{real[c]:.4f}" for c in _REAL_COLS]
        cells.append(f"{r['AITS_s']:.2f}" if "AITS_s" in r else "-")
        lines.append("| " + " | ".join(cells) + " |")
    m = results["paper"]
    lines += ["", f"For reference, {m['method']}: Traj. err 50cm {m['Traj_err_50cm']}, Loc. err 50cm "
                  f"{m['Loc_err_50cm']}, Avg. err {m['Avg_err_m']} m, R-precision top-3 {m['R_precision_top3']}, "
                  f"FID {m['FID']}, AITS {m['AITS_s']} s (different data, evaluator and hardware: only the control "
                  "errors, in metres, compare directly).", ""]
    ratios = [(n, r["R_precision_vs_unconstrained"]) for n, r in results["rows"].items()
              if "R_precision_vs_unconstrained" in r]
    if ratios:
        lines.append("R-precision relative to unconstrained generation (top-1 / top-3; target ≥ 0.90): "
                     + "; ".join(f"{n}: {v['top1']:.2f} / {v['top3']:.2f}" for n, v in ratios) + ".")
    lines += ["", f"Protocol: {p['samples']} motions of `{p['dataset']}` (at most {p['max_frames']} frames, "
                  f"multiples of 4), one caption each; control = the real {', '.join(p['joints'])} position at "
                  f"{p['density']} density; {p['steps']} {p.get('sampler', 'ddim')} steps, CFG {p['cfg']}, seed {p['seed']}"
                  + _unconstrained_sampling(p) + ". Traj. err: share of motions "
                  "with any controlled location off by more than the threshold; Loc. err: mean share of controlled "
                  "locations off by more; Avg. err: mean distance (m, ± 95% CI over motions). R-precision within "
                  f"pools of {p['pool']}" + (" (easier than the usual 32)" if p["pool"] < MAX_POOL else "") +
                  f"; FID against all {p['reference_motions']} real motions of the split; evaluator embeddings are "
                  "unit-norm, so FID, MM-Dist "
                  f"and Diversity are on a smaller scale than in the papers. AITS on {_where(p)}. "
                  f"Total time {results['time_s']:.0f} s."]
    return "\n".join(lines) + "\n"


def write_control_report(results: dict[str, Any], out_dir: str | Path) -> Path:
    """results.json and report.md in `out_dir` (written atomically); returns the report's path."""
    out = Path(out_dir)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    path = out / "report.md"
    atomic_write_text(path, markdown_report(results))
    return path
