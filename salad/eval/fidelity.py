"""Motion fidelity per trained action: does a held-out paraphrase of each action make a motion that
measures like the real captures of that action?

For every class (a content label, plus the walking styles that change speed) the model generates
from each held-out paraphrase (salad.eval.paraphrases) with several seeds at automatic length, and
the generated motions are measured the same way as the real clips of that class in the style the
prompt asks for ("normal" for a prompt that names none: an unstyled wave is an ordinary wave, not the
mix of elderly and energetic ones the class holds), from the test split, widened to all splits and
then (unstyled prompts) to every clip of the class where fewer than MIN_REFERENCE clips are found;
durations are capped at the model's longest motion. Each class passes or fails on the checks that
matter for it, with the tolerances in RULES, stated before anything is measured.
The table is made twice from the same samples: the raw decoder output, and the output after the
clean-up (salad.motion.cleanup: rigid bones, then the foot lock) that generate() applies by default.

    salad eval-fidelity --data data/bandai-hml --out DIR [--seeds 3] [--steps 50] [--prompt-set b]
"""
from __future__ import annotations

import copy
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..files import shown_path
from ..motion import skeleton as sk
from ..motion.cleanup import clean_motion
from ..motion.representation import FPS, features_to_joints
from . import physics
from ..data.dataset import read_captions
from ..data.labels import read_labels
from ..diffusion.sampling import describe_settings
from .paraphrases import PROMPT_SETS

MIN_REFERENCE = 4
UNSTYLED = "normal"          # the style label of clips whose captions name no manner
SIDE_SHARE = 0.35        # a wrist with under this share of the two wrists' travel is not acting

# check -> (rule in words, test(generated median, real median) or for "side" the share of matching motions)
RULES: dict[str, str] = {
    "duration_s": "auto length within ±35% of the real median",
    "root_speed_mps": "within ±30% of the real median, or ±0.15 m/s",
    "turn_deg": "within ±40% of the real median, or ±30°",
    "side": "at least 2 of 3 motions act with the hand their prompt names (left / right / both), or where it "
            "names none the real clips' majority hand",
    "hand_height_m": "within ±0.15 m of the real median",
    "leg_lift_m": "at least 70% of the real median",
    "bow_depth_m": "at least 60% of the real median",
    "still_foot_share": "at least 80% of the real median (raw); at least 95% after the foot lock",
    "jerk_mps3": "at most twice the real median",
}

LOCOMOTION = ("walk", "walk-back", "walk-left", "walk-right", "walk-turn-left", "walk-turn-right")
HANDS = ("wave-left-hand", "wave-right-hand", "wave-both-hands", "raise-up-left-hand", "raise-up-right-hand",
         "raise-up-both-hands", "bye", "byebye", "guide", "respond", "call")


def checks_for(content: str) -> tuple[str, ...]:
    if content in LOCOMOTION:
        return ("duration_s", "root_speed_mps", "turn_deg", "still_foot_share", "jerk_mps3")
    if content in ("run", "dash"):
        return ("duration_s", "root_speed_mps", "turn_deg", "jerk_mps3")
    if content in HANDS:
        return ("duration_s", "root_speed_mps", "side", "hand_height_m", "jerk_mps3")
    if content == "kick":
        return ("duration_s", "leg_lift_m", "jerk_mps3")
    if content == "bow":
        return ("duration_s", "bow_depth_m", "jerk_mps3")
    return ("duration_s", "root_speed_mps", "jerk_mps3")


@dataclass(frozen=True)
class FidelityClass:
    key: str                 # "walk" or "walk/exhausted"
    content: str
    style: str | None
    prompts: tuple[str, ...]
    checks: tuple[str, ...]


def fidelity_classes(keys=None, prompt_set: str = "a") -> list[FidelityClass]:
    """The benchmark's classes (all, or those named in `keys`) with the prompts of one held-out set."""
    if prompt_set not in PROMPT_SETS:
        raise ValueError(f"unknown prompt set {prompt_set!r}; known: {', '.join(PROMPT_SETS)}")
    out = []
    for key, prompts in PROMPT_SETS[prompt_set].items():
        if keys and key not in keys:
            continue
        content, _, style = key.partition("/")
        out.append(FidelityClass(key, content, style or None, prompts, checks_for(content)))
    if keys:
        unknown = sorted(set(keys) - set(PROMPT_SETS[prompt_set]))
        if unknown:
            raise ValueError(f"unknown fidelity classes {unknown}; known: {', '.join(PROMPT_SETS[prompt_set])}")
    return out


# ---------------------------------------------------------------- measures

def acting_side(measures: dict) -> str:
    left, right = measures["left_wrist_path_m"], measures["right_wrist_path_m"]
    share = left / max(left + right, 1e-9)
    return "left" if share > 1 - SIDE_SHARE else "right" if share < SIDE_SHARE else "both"


def measure(joints: np.ndarray, fps: float = FPS) -> dict:
    """Everything the fidelity checks read from one motion (T, 22, 3)."""
    j = physics.check_joints(joints)
    checks = physics.physical_checks(j, fps)
    floor = j[:, :, 1].min()
    ankles = j[:, [sk.FOOT_JOINTS_LEFT[0], sk.FOOT_JOINTS_RIGHT[0]], 1] - floor
    head = j[:, sk.JOINT_NAMES.index("head"), 1]
    k = max(1, min(5, len(j) // 4))
    jerk = np.diff(j, n=3, axis=0) * fps ** 3 if len(j) > 3 else np.zeros((1,) + j.shape[1:])
    return {
        "duration_s": len(j) / fps,
        "root_speed_mps": checks["root_speed_mps"],
        "turn_deg": checks["turn_deg"],
        "side": acting_side(checks),
        "left_wrist_path_m": checks["left_wrist_path_m"],
        "right_wrist_path_m": checks["right_wrist_path_m"],
        "hand_height_m": max(checks["left_wrist_height_m"], checks["right_wrist_height_m"]),
        "leg_lift_m": float(ankles.max()),
        "bow_depth_m": float(max(0.0, head[:k].mean() - head.min())),
        "still_foot_share": physics.still_foot_share(j, fps),
        "contact_slide_share": physics.contact_slide_share(j, fps),
        "jerk_mps3": float(np.linalg.norm(jerk, axis=-1).mean()),
    }


def _median(rows: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in rows]))


def majority_side(rows: list[dict]) -> str:
    sides = [r["side"] for r in rows]
    return max(("left", "right", "both"), key=sides.count)


_SIDE_WORDS = {"left": "left", "right": "right", "both": "both", "two": "both"}


def named_side(prompt: str) -> str | None:
    """The hand a prompt asks for ("left", "right", "both"), None where it names none or several.
    It decides the side check where it can: classes such as bye hold every capture with its
    mirror image, so their real clips act with either hand as often."""
    named = {_SIDE_WORDS[w] for w in re.findall(r"[a-z]+", prompt.lower()) if w in _SIDE_WORDS}
    return named.pop() if len(named) == 1 else None


def judge(check: str, real: list[dict], gen: list[dict], cleaned: bool = False,
          sides: list[str | None] | None = None) -> dict:
    """One check of one class: real and generated values and whether it passes RULES[check], with its
    margin: how far inside (> 0) or outside (< 0) the rule the generated value lies, as a share of the
    rule's tolerance, clipped to [-1, 1] (what validate_actions scores checkpoints by).
    sides: for "side", the hand each generated motion's prompt names (None: the real clips' majority)."""
    if check == "side":
        wants = [s or majority_side(real) for s in (sides or [None] * len(gen))]
        share = float(np.mean([r["side"] == w for r, w in zip(gen, wants, strict=True)]))
        slack, scale = share - (2 / 3 - 1e-9), 2 / 3
        shown = {"real": "/".join(sorted(set(wants))), "generated": round(share, 3)}
    else:
        r, g = _median(real, check), _median(gen, check)
        slack, scale = _slack(check, r, g, cleaned)
        shown = {"real": round(r, 4), "generated": round(g, 4)}
    margin = slack / scale if scale > 0 else float(np.sign(slack))
    return {**shown, "pass": bool(slack >= 0), "margin": float(np.clip(margin, -1.0, 1.0))}


def _slack(check: str, r: float, g: float, cleaned: bool) -> tuple[float, float]:
    """(how far g is inside RULES[check] around the real median r, the rule's tolerance): it passes
    where the first is >= 0."""
    if check == "duration_s":
        return 0.35 - abs(g / r - 1), 0.35
    if check in ("root_speed_mps", "turn_deg"):
        tol = max(0.3 * abs(r), 0.15) if check == "root_speed_mps" else max(0.4 * abs(r), 30.0)
        return tol - abs(g - r), tol
    if check == "hand_height_m":
        return 0.15 - abs(g - r), 0.15
    floors = {"leg_lift_m": 0.7, "bow_depth_m": 0.6, "still_foot_share": 0.95 if cleaned else 0.8}
    if check in floors:
        return g - floors[check] * r, floors[check] * r
    if check == "jerk_mps3":
        return 2.0 * r - g, 2.0 * r
    raise KeyError(f"unknown check {check!r}")


# ---------------------------------------------------------------- data

def reference_clips(data_root: str | Path, cls: FidelityClass, labels: dict, split: str = "test"
                    ) -> tuple[list[np.ndarray], str]:
    """Joints of the real clips of a class (from their features, as generated motions are made),
    and which splits they came from."""
    root = Path(data_root)

    def pick(splits, style):
        return sorted(k for k, lab in labels.items() if lab.content == cls.content and lab.split in splits
                      and (style is None or lab.style == style))

    style = cls.style or UNSTYLED
    every = {"train", "val", "test"}
    tries = [({split}, style, split), (every, style, "all")]
    if cls.style is None:
        # Too few unstyled takes: the class as captured, every style of every split. The test split alone
        # would hold 2-3 of the class's ~15 styles, whichever the split drew (for bye: childish and musical,
        # hand height 0.80 m and jerk 85 m/s³, where all 30 clips have medians of 0.69 m and 7.5 m/s³).
        tries.append((every, None, "all, all styles"))
    for splits, wanted, used in tries:
        names = pick(splits, wanted)
        if len(names) >= MIN_REFERENCE:
            break
    clips = []
    for name in names:
        f = np.load(root / "new_joint_vecs" / f"{name}.npy")
        clips.append(features_to_joints(f.astype(np.float32)))
    return clips, used


# ---------------------------------------------------------------- the benchmark

def evaluate_fidelity(pipe, data_root: str | Path, seeds: int = 3, steps: int | None = None, cfg: float = 7.5,
                      sampler: str = "ddim", classes=None, split: str = "test", classifier=None,
                      progress: Callable[[int, int], None] | None = None, length: str = "auto",
                      prompt_set: str = "a", first_seed: int = 0) -> dict:
    """Per-class checks of generated against real motion; with a `classifier` (salad.eval.classifiers), also
    the share of generated motions it puts in the prompt's action (and style, for styled classes).
    length: "auto", "model" or "prior" (Pipeline.frames_for). The seeds are first_seed ... first_seed +
    seeds - 1: other seeds than the default 0, 1, 2 show how far the table moves by chance alone."""
    if length not in ("auto", "model", "prior"):
        raise ValueError(f"length must be 'auto', 'model' or 'prior', got {length!r}")
    from ..pipeline import AUTO_LENGTH_BAND
    if not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"seeds must be a positive integer, got {seeds!r}")
    if not isinstance(first_seed, int) or first_seed < 0:
        raise ValueError(f"first_seed must be a non-negative integer, got {first_seed!r}")
    steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler)     # the report names the steps used
    labels = read_labels(data_root)
    present = {lab.content for lab in labels.values()}
    todo = [c for c in fidelity_classes(classes, prompt_set) if c.content in present]
    if not todo:
        raise ValueError(f"{data_root}: none of the fidelity classes is in this dataset")
    total = sum(len(c.prompts) for c in todo) * seeds
    done, started = 0, time.perf_counter()
    rows = []
    for cls in todo:
        reference = reference_measures(data_root, cls, labels, split, pipe.max_seconds)
        if not reference["clips"]:
            continue
        raw, clean, samples, features = [], [], [], []
        for prompt in cls.prompts:
            for seed in range(first_seed, first_seed + seeds):
                m = pipe.generate(prompt, seconds=length, seed=seed, steps=steps, cfg=cfg, sampler=sampler,
                                  foot_lock=False)
                locked, _ = clean_motion(m.joints, m.features)
                raw.append(measure(m.joints))
                clean.append(measure(locked))
                features.append(m.features)
                # every measure is kept, so that the table can be judged again under other rules
                samples.append({"prompt": prompt, "seed": seed, "frames": m.frames, "raw": raw[-1],
                                "clean": clean[-1]})
                done += 1
                if progress:
                    progress(done, total)
        row = {"class": cls.key, "reference": reference, "samples": samples}
        judge_row(row)
        if classifier is not None:
            row["classified"] = classified(classifier, cls, features)
            for sample, content in zip(samples, row["classified"]["predicted"]):
                sample["classified_as"] = content
        rows.append(row)
    return {"rows": rows, "rules": RULES, "settings": {
        "seeds": seeds, "first_seed": first_seed, "steps": steps, "cfg": cfg, "sampler": sampler, **pipe.sampler_settings(sampler),
        "split": split, "max_seconds": pipe.max_seconds, "model": shown_path(pipe.source),
        "length": length, "length_band": AUTO_LENGTH_BAND if length == "auto" else None, "prompt_set": prompt_set, "seconds": round(time.perf_counter() - started, 1)},
        "summary": summary(rows, classifier)}


def validate_actions(pipe, data_root: str | Path, contents, captions: int = 4, seeds: int = 8,
                     first_seed: int = 100, sampler: str = "consistency") -> dict:
    """The fidelity checks of the unstyled classes `contents` on motions generated from their training
    captions (up to `captions` of them, drawn with a fixed seed), raw: without the planted-feet refinement
    or the clean-up, seeds first_seed ... first_seed + seeds - 1. A validation score for choosing among a
    run's checkpoints that leaves the benchmark's held-out paraphrases and seeds unseen. Per class: its
    checks, whether it passes, and its margin (its worst check's); over the classes: `passed`, `margin`
    (the classes' mean) and `score` = passed + 0.49 * margin, i.e. the most classes passed, then the
    widest margins."""
    labels = read_labels(data_root)
    by_key = {c.key: c for c in fidelity_classes(None, "a")}
    unknown = sorted(set(contents) - set(by_key))
    if unknown:
        raise ValueError(f"no fidelity class for {unknown}; classes: {', '.join(sorted(by_key))}")
    classes = {}
    for content in contents:
        cls, pool = by_key[content], []
        for name in sorted(n for n, lab in labels.items() if lab.content == content and lab.split == "train"):
            path = Path(data_root) / "texts" / f"{name}.txt"
            for c in read_captions(path) if path.is_file() else []:
                if c.text not in pool:
                    pool.append(c.text)
        if not pool:
            raise ValueError(f"{data_root}: no training captions of {content!r}")
        picked = np.random.default_rng(0).choice(len(pool), min(captions, len(pool)), replace=False)
        prompts = [pool[i] for i in sorted(picked)]
        real = reference_measures(data_root, cls, labels, "train", pipe.max_seconds)["measures"]
        gen, sides = [], []
        for prompt in prompts:
            for seed in range(first_seed, first_seed + seeds):
                m = pipe.generate(prompt, seconds="auto", seed=seed, sampler=sampler, foot_lock=False,
                                  foot_refine=False)
                gen.append(measure(m.joints))
                sides.append(named_side(prompt))
        checks = {c: judge(c, real, gen, sides=sides) for c in cls.checks}
        classes[content] = {"checks": checks, "pass": all(v["pass"] for v in checks.values()),
                            "margin": min(v["margin"] for v in checks.values()), "motions": len(gen)}
    passed = sum(c["pass"] for c in classes.values())
    margin = float(np.mean([c["margin"] for c in classes.values()]))
    return {"classes": classes, "passed": passed, "margin": round(margin, 4),
            "score": round(passed + 0.49 * margin, 4)}


def judge_row(row: dict) -> dict:
    """Judge one class's row from the measures it keeps (its real clips' and every sample's), raw and
    after the clean-up, under the current RULES; so that a stored table can be judged again."""
    real, samples = row["reference"]["measures"], row["samples"]
    checks = checks_for(row["class"].partition("/")[0])
    sides = [named_side(s["prompt"]) for s in samples]
    for name in ("raw", "clean"):
        gen = [s[name] for s in samples]
        judged = {c: judge(c, real, gen, cleaned=name == "clean", sides=sides) for c in checks}
        row[name] = {"checks": judged, "pass": all(v["pass"] for v in judged.values()),
                     "contact_slide_share": round(_median(gen, "contact_slide_share"), 4)}
    row["real_contact_slide_share"] = round(_median(real, "contact_slide_share"), 4)
    return row


def reference_measures(data_root: str | Path, cls: FidelityClass, labels: dict, split: str,
                       max_seconds: float) -> dict:
    """A row's reference: its real clips (reference_clips), where they came from, and their measures."""
    clips, used = reference_clips(data_root, cls, labels, split)
    real = [measure(j) for j in clips]
    # the model makes at most its canvas: a longer capture counts as a full-canvas motion
    for r in real:
        r["duration_s"] = min(r["duration_s"], max_seconds)
    return {"clips": len(clips), "splits": used, "measures": real}


def rejudge(results: dict, data_root: str | Path | None = None) -> dict:
    """A stored fidelity result judged again under the current RULES (same samples, same classifier
    reads); the rules it was judged by before are replaced. With data_root, each row's real clips are
    chosen and measured again too, under the current reference_clips (runs stored before their settings
    kept max_seconds were all made on 196-frame canvases). `results` itself is left as it was."""
    results = copy.deepcopy(results)
    if data_root is not None:
        labels = read_labels(data_root)
        settings = results["settings"]
        cap = settings.get("max_seconds", 196 / FPS)
        by_key = {c.key: c for c in fidelity_classes(None, settings.get("prompt_set", "a"))}
        for row in results["rows"]:
            row["reference"] = reference_measures(data_root, by_key[row["class"]], labels,
                                                  settings.get("split", "test"), cap)
    rows = [judge_row(r) for r in results["rows"]]
    summ = summary(rows)
    if "classified" in results["summary"]:
        summ["classified"] = results["summary"]["classified"]
    return {**results, "rows": rows, "rules": RULES, "summary": summ}


# settings that may differ between runs pooled into one table: the seeds, and what the runs recorded of themselves
POOLED_MAY_DIFFER = ("seeds", "first_seed", "seconds", "pooled_seeds")


def pool(runs: list[dict]) -> dict:
    """Stored runs of the same classes, prompts and settings with other seeds, as one run whose rows hold
    every run's samples (judged again with rejudge: medians over all their seeds). Each run's seeds must
    be its own, and the classifier's reads add up. `runs` are left as they were."""
    if not runs:
        raise ValueError("no runs to pool")
    first = runs[0]
    same = {k: v for k, v in first["settings"].items() if k not in POOLED_MAY_DIFFER}
    seeds: set[int] = set()
    for run in runs:
        theirs = {k: v for k, v in run["settings"].items() if k not in POOLED_MAY_DIFFER}
        if theirs != same:
            differ = sorted(k for k in set(theirs) | set(same) if theirs.get(k) != same.get(k))
            raise ValueError(f"only runs of the same settings pool; these differ: {', '.join(differ)}")
        if [r["class"] for r in run["rows"]] != [r["class"] for r in first["rows"]]:
            raise ValueError("only runs of the same classes pool")
        mine = {s["seed"] for r in run["rows"] for s in r["samples"]}
        if mine & seeds:
            raise ValueError(f"runs share seeds {sorted(mine & seeds)}: each motion would count twice")
        seeds |= mine
    pooled = copy.deepcopy(first)
    for run in runs[1:]:
        for row, more in zip(pooled["rows"], run["rows"]):
            row["samples"] += copy.deepcopy(more["samples"])
            if "classified" in row and "classified" in more:
                for k in ("content_correct", "total", "style_correct"):
                    if k in row["classified"]:
                        row["classified"][k] += more["classified"][k]
                row["classified"]["predicted"] = row["classified"]["predicted"] + more["classified"]["predicted"]
            else:                   # a run judged without the classifier: no count covers every motion
                row.pop("classified", None)
    reads = [r["summary"].get("classified") for r in runs]
    if all(reads):
        correct, total = sum(c["content_correct"] for c in reads), sum(c["total"] for c in reads)
        pooled["summary"]["classified"] = {**reads[0], "content_correct": correct, "total": total,
                                           "share": round(correct / total, 4) if total else None}
    else:
        pooled["summary"].pop("classified", None)
    s = pooled["settings"]
    s["seeds"], s["first_seed"] = len(seeds), min(seeds)
    s["pooled_seeds"] = sorted(seeds)
    s["seconds"] = round(sum(r["settings"].get("seconds", 0.0) for r in runs), 1)
    return pooled


def classified(classifier, cls: FidelityClass, features: list) -> dict:
    """How many of a class's generated motions the classifier calls the prompt's action (and style)."""
    pred = classifier.predict(features)
    content_ok = [p == cls.content for p in pred["content"]]
    out = {"predicted": list(pred["content"]), "content_correct": sum(content_ok), "total": len(features)}
    if cls.style is not None and "style" in pred:
        out["style_correct"] = sum(p == cls.style for p in pred["style"])
    return out


def summary(rows: list[dict], classifier=None) -> dict:
    out = {v: {"passed": sum(r[v]["pass"] for r in rows), "classes": len(rows)} for v in ("raw", "clean")}
    if classifier is not None:
        correct = sum(r["classified"]["content_correct"] for r in rows)
        total = sum(r["classified"]["total"] for r in rows)
        out["classified"] = {"content_correct": correct, "total": total,
                             "share": round(correct / total, 4) if total else None,
                             "classifier": shown_path(getattr(classifier, "meta", {}).get("path", "?"))}
    return out


def _values(check: str, v: dict) -> str:
    if check == "side":
        return f"{v['generated']:.2f} {v['real']}"
    fmt = "{:.0f}" if check == "turn_deg" else "{:.2f}"
    return f"{fmt.format(v['generated'])} / {fmt.format(v['real'])}"


def _cell(check: str, v: dict) -> str:
    return _values(check, v) + ("" if v["pass"] else " ✗")


def _classified_cell(c: dict) -> str:
    cell = f"{c['content_correct']}/{c['total']}"
    return cell + (f", style {c['style_correct']}/{c['total']}" if "style_correct" in c else "")


def describe_length(settings: dict) -> str:
    """How a report names its length setting (reports from before the band record "auto" without one)."""
    length, band = settings.get("length"), settings.get("length_band")
    if length == "prior":
        return "the length prior"
    if length == "auto" and band:
        return f"auto length held within ×/÷{band:g} of the length prior"
    return "auto length (the model's own)" if length == "model" else "auto length"


def describe_seeds(s: dict) -> str:
    first = s.get("first_seed", 0)
    if s.get("pooled_seeds") and s["pooled_seeds"] != list(range(first, first + s["seeds"])):
        return f"{s['seeds']} seeds ({', '.join(map(str, s['pooled_seeds']))})"
    return f"{s['seeds']} seeds" if not first else f"{s['seeds']} seeds ({first}-{first + s['seeds'] - 1})"


# how a comparison table names a failed check
CHECK_NAMES = {"duration_s": "length", "root_speed_mps": "speed", "turn_deg": "turn", "side": "side",
               "hand_height_m": "hand", "leg_lift_m": "leg lift", "bow_depth_m": "bow depth",
               "still_foot_share": "still foot", "jerk_mps3": "jerk"}


def _failures_cell(v: dict) -> str:
    if v["pass"]:
        return "✓"
    failed = [f"{CHECK_NAMES.get(c, c)} {_values(c, r)}" for c, r in v["checks"].items() if not r["pass"]]
    return "✗ " + ", ".join(failed)


def compare_markdown(runs: list[tuple[dict, str]]) -> str:
    """Several runs side by side: a row per class, a column per (results, "raw" or "clean"); a cell is ✓
    where the class passes, else its failing checks, generated / real median ("–": the run has no such class).
    The results are judged as they stand (rejudge them first for the current rules)."""
    if not runs:
        raise ValueError("nothing to compare")
    heads, classes = [], []
    for results, variant in runs:
        if variant not in ("raw", "clean"):
            raise ValueError(f"a column is the raw or the clean table, got {variant!r}")
        s = results["settings"]
        heads.append(f"set {s.get('prompt_set', 'a')}, {s['sampler']} {s['steps']}, {describe_seeds(s)}, "
                     + ("raw" if variant == "raw" else "after the foot lock"))
        classes += [r["class"] for r in results["rows"] if r["class"] not in classes]
    lines = ["| class | " + " | ".join(heads) + " |", "|---|" + "---|" * len(runs)]
    for cls in classes:
        cells = []
        for results, variant in runs:
            row = next((r for r in results["rows"] if r["class"] == cls), None)
            cells.append("–" if row is None else _failures_cell(row[variant]))
        lines.append(f"| {cls} | " + " | ".join(cells) + " |")
    lines.append("| classes passed | " + " | ".join(
        f"**{r['summary'][v]['passed']} / {r['summary'][v]['classes']}**" for r, v in runs) + " |")
    read = [r["summary"].get("classified") for r, _ in runs]
    if any(read):
        lines.append("| read as their action | " + " | ".join(
            f"{100 * c['share']:.1f}%" if c else "–" for c in read) + " |")
    return "\n".join(lines) + "\n"


def report_markdown(results: dict) -> str:
    s = results["settings"]
    lines = ["# Fidelity per class", "",
             f"Model `{s['model']}`; held-out paraphrases (set {s.get('prompt_set', 'a')}) × {describe_seeds(s)}, "
             f"{describe_length(s)}, {s['sampler']} "
             f"{s['steps']} steps{describe_settings(s)}, CFG {s['cfg']}; reference: real clips of the class in the prompt's style "
             f"({UNSTYLED} where it names none) from the {s['split']} split, widened to all splits, then all "
             f"styles, where fewer than {MIN_REFERENCE} are found (in brackets). Cells: generated median / real median; "
             "✗ marks a failed check; side: share of motions acting with the hand their prompt names (else the "
             "real clips' majority hand), then that hand.", "",
             "Rules:", ""]
    lines += [f"- `{k}`: {v}" for k, v in results["rules"].items()]
    clf = results["summary"].get("classified")
    if clf:
        lines += ["", f"The classifier (`{clf['classifier']}`) puts {clf['content_correct']} of {clf['total']} raw motions "
                  f"({100 * clf['share']:.0f}%) in the prompt's action; per class in the column `classified` "
                  "(action, then style for styled classes)."]
    checks = list(RULES)
    for variant in ("raw", "clean"):
        summ = results["summary"][variant]
        title = "raw decoder output" if variant == "raw" else "after the foot lock"
        lines += ["", f"## {title}: {summ['passed']} of {summ['classes']} classes pass", "",
                  "| class | ref. clips | pass | " + " | ".join(checks) + " | contact slide |"
                  + (" classified |" if clf else ""),
                  "|---|---|---|" + "---|" * (len(checks) + 1) + ("---|" if clf else "")]
        for r in results["rows"]:
            v = r[variant]
            cells = [_cell(c, v["checks"][c]) if c in v["checks"] else "" for c in checks]
            used = r["reference"]["splits"]
            ref = f"{r['reference']['clips']}" + ("" if used == s["split"] else f" ({used})")
            lines.append(f"| {r['class']} | {ref} | {'yes' if v['pass'] else '**no**'} | " + " | ".join(cells)
                         + f" | {v['contact_slide_share']:.2f} / {r['real_contact_slide_share']:.2f} |"
                         + (f" {_classified_cell(r['classified'])} |" if clf else ""))
    return "\n".join(lines) + "\n"
