"""`salad eval` (the T2M protocol) and the benchmarks `salad eval-control`, `eval-edit`,
`eval-fidelity`, `eval-length`, `eval-real-edit`, `eval-vae` and `eval-classifier`."""
from __future__ import annotations

import argparse
import itertools
import json
import re
from pathlib import Path

from ..eval import EMBEDDED_CLASSIFIER, EMBEDDED_EVALUATOR
from ..eval.edit_suite import DEFAULT_SCALES, MODES, SUITES, default_suite
from ..eval.paraphrases import PROMPT_SETS
from ..files import atomic_write_text, shown_path
from .common import add_device, add_sampling, apply_sampling, device_of, progress_bar

# Spelled out to keep the CLI free of torch; a test checks them against salad.eval.control_bench.OMNICONTROL_JOINTS,
# salad.eval.length_dist.DEFAULT_BIN_FRAMES and salad.eval.real_edit_bench.SDEDIT_STRENGTHS.
OMNICONTROL_JOINTS = ("pelvis", "left_foot", "right_foot", "head", "left_wrist", "right_wrist")
DEFAULT_BIN_FRAMES = 8
SDEDIT_STRENGTHS = (0.3, 0.5, 0.7)


def cmd_eval(a) -> int:
    import torch
    from ..data.dataset import MotionDataset
    from ..eval.evaluator import load_evaluator
    from ..eval.generators import ModelGenerator, VAEReconstruction
    from ..eval.t2m import evaluate_t2m, ground_truth_generator, write_report
    from ..pipeline import load_pipeline
    device = device_of(a)
    if a.threads:
        torch.set_num_threads(a.threads)
    ev = load_evaluator(a.evaluator)
    ds = MotionDataset(a.data, a.split, max_frames=10 ** 9)
    partial = Path(a.out) / "partial"      # finished repeats, so that a rerun resumes
    rows = {"Real motion": evaluate_t2m(ground_truth_generator(ds), ds, ev, repeats=a.repeats, seed=a.seed,
                                        progress=True)}
    for model in [] if a.real_only else a.model or [None]:
        pipe = load_pipeline(model, bf16=not a.fp32, device=device)
        apply_sampling(pipe, a)
        name = "SALAD (embedded)" if model is None else f"SALAD ({Path(model).name})"
        vae = VAEReconstruction(pipe)
        rows[f"{name} VAE reconstruction"] = evaluate_t2m(vae, ds, ev, repeats=1, seed=a.seed, progress=True)
        rows[f"{name} VAE reconstruction"]["MPJPE_m"] = vae.mpjpe_m
        gen = ModelGenerator(pipe, steps=a.steps, sampler=a.sampler, cfg=a.cfg, seed=a.seed)
        rows[name] = evaluate_t2m(gen, ds, ev, repeats=a.repeats, seed=a.seed, mm_prompts=a.mm_prompts,
                                  mm_repeats=a.mm_repeats, progress=True,
                                  state_file=partial / f"{re.sub(r'[^A-Za-z0-9]+', '-', name).strip('-')}.json")
    path = write_report(rows, a.out)
    print(path.read_text())
    return 0


def add_eval(sub) -> None:
    ev = sub.add_parser("eval", help="T2M protocol: FID, R-precision, MM-Dist, Diversity, MultiModality")
    ev.add_argument("--evaluator", default=str(EMBEDDED_EVALUATOR),
                    help="evaluator checkpoint directory (default: the one shipped in assets/eval)")
    ev.add_argument("--data", required=True, help="HumanML3D-layout dataset")
    ev.add_argument("--model", action="append", help="model directory (default: the embedded model); repeatable")
    ev.add_argument("--real-only", action="store_true", help="score only the real motions (the reference row)")
    ev.add_argument("--split", default="test")
    ev.add_argument("--repeats", type=int, default=20)
    add_sampling(ev)
    ev.add_argument("--mm-prompts", type=int, default=32)
    ev.add_argument("--mm-repeats", type=int, default=10)
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--threads", type=int, default=0)
    ev.add_argument("--fp32", action="store_true",
                    help="disable bf16 autocast (CPUs without bf16 run fp32 anyway); a run resumes only in the precision it started in")
    ev.add_argument("--out", required=True, help="directory for results.json and report.md")
    add_device(ev)
    ev.set_defaults(func=cmd_eval)


def _float_list(text: str, what: str) -> list[float]:
    try:
        items = [float(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        raise ValueError(f"--{what}: cannot read {text!r} as a comma list of numbers") from None
    if not items:
        raise ValueError(f"--{what} is empty")
    return items


def add_eval_control(sub) -> argparse.ArgumentParser:
    """Register `eval-control` on the CLI's subparsers."""
    p = sub.add_parser("eval-control", help="path-following benchmark: Traj/Loc/Avg err, FID, R-precision, AITS",
                       description="Path-following benchmark. --ddim-eta, --cfg-rescale and --cfg-cutoff set how the "
                                   "Unconstrained row samples; the guided rows run deterministic DDIM with guidance at "
                                   "every step (MoLA's sampler).")
    p.add_argument("--data", required=True, help="HumanML3D-layout dataset")
    p.add_argument("--evaluator", default=str(EMBEDDED_EVALUATOR),
                   help="evaluator checkpoint directory (default: the one shipped in assets/eval)")
    p.add_argument("--out", required=True, help="directory for results.json and report.md")
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--split", default="test", help="split to draw motions from (tune on val, report on test)")
    p.add_argument("--samples", type=int, default=32, help="motions to control")
    p.add_argument("--joints", default="pelvis",
                   help=f"comma list of joints to control, e.g. {','.join(OMNICONTROL_JOINTS)}")
    p.add_argument("--density", default="100%", help="controlled frames: '100%%', '25%%' or a count such as 1, 2, 5")
    p.add_argument("--strength", default="1", help="guidance strength; comma lists here and below make one row "
                                                   "per combination")
    p.add_argument("--gradient-steps", default=None, help="guidance steps per network evaluation")
    p.add_argument("--refine-steps", default=None, help="guidance steps on the final latent")
    p.add_argument("--repeats", default=None, help="time-travel repeats per step (default: 1-3 by phase)")
    add_sampling(p, ("ddim", "consistency"))
    p.add_argument("--max-frames", type=int, default=196)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    p.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    add_device(p)
    p.set_defaults(func=cmd_eval_control)
    return p


def cmd_eval_control(a) -> int:
    from ..data.dataset import MotionDataset
    from ..eval.control_bench import evaluate_control, parse_density, parse_joints, write_control_report
    from ..pipeline import load_pipeline
    from ..eval.evaluator import load_evaluator

    device = device_of(a)
    joints = parse_joints(a.joints)
    parse_density(a.density)
    options = {"strength": _float_list(a.strength, "strength")}
    for key in ("gradient_steps", "refine_steps", "repeats"):
        text = getattr(a, key)
        if text is not None:
            options[key] = [int(v) for v in _float_list(text, key.replace("_", "-"))]
    settings = [dict(zip(options, combo)) for combo in itertools.product(*options.values())]
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    ev = load_evaluator(a.evaluator)
    ds = MotionDataset(a.data, a.split, max_frames=10 ** 9)
    pipe = load_pipeline(a.model, bf16=not a.fp32, threads=a.threads or None, device=device)
    apply_sampling(pipe, a)
    res = evaluate_control(pipe, ds, ev, samples=a.samples, steps=a.steps, cfg=a.cfg, sampler=a.sampler,
                           settings=settings,
                           joints=joints, density=a.density, seed=a.seed, max_frames=a.max_frames,
                           progress=lambda msg: print(msg, flush=True))
    res["protocol"].update(model=shown_path(pipe.source), split=a.split, evaluator=shown_path(a.evaluator))
    path = write_control_report(res, out)
    print(path.read_text())
    print(f"wrote {out / 'results.json'} and {path}")
    return 0


def add_eval_edit(sub) -> argparse.ArgumentParser:
    """Register `eval-edit` on the CLI's subparsers."""
    p = sub.add_parser("eval-edit", help="editing benchmark: success and preservation of attention edits vs "
                                         "plain regeneration")
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--classifier", default=str(EMBEDDED_CLASSIFIER),
                   help="content/style/side classifier checkpoint (default: the one shipped in assets/eval)")
    p.add_argument("--out", required=True, help="directory for results.json and report.md")
    p.add_argument("--seeds", type=int, default=5, help="seeds per case")
    p.add_argument("--seed", type=int, default=0, help="first seed")
    add_sampling(p)
    p.add_argument("--modes", default=",".join(MODES), help=f"comma list of {', '.join(MODES)}")
    p.add_argument("--suite", choices=SUITES, default="tuned",
                   help="tuned (default): the cases the editing defaults were chosen on; held-out: the same kinds "
                        "of edit in other wording, never used for tuning")
    p.add_argument("--scales", default=",".join(f"{s:g}" for s in DEFAULT_SCALES),
                   help="re-weighting scales, comma list in [-3, 3]")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    p.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    add_device(p)
    p.set_defaults(func=cmd_eval_edit)
    return p


def _parse_list(text: str, what: str, kind=str) -> list:
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise ValueError(f"--{what} is empty")
    try:
        return [kind(t) for t in items]
    except ValueError:
        raise ValueError(f"--{what}: cannot read {text!r} as a comma list of numbers") from None


def cmd_eval_edit(a) -> int:
    from ..eval.classifiers import load_classifier
    from ..eval.edit_bench import run_edit_benchmark
    from ..pipeline import load_pipeline
    from ..eval.edit_report import format_report, write_results

    device = device_of(a)
    modes = _parse_list(a.modes, "modes")
    scales = _parse_list(a.scales, "scales", float)
    cases = default_suite(modes, a.suite)
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    clf = load_classifier(a.classifier)
    clf.meta["path"] = str(a.classifier)
    pipe = load_pipeline(a.model, bf16=not a.fp32, threads=a.threads or None, device=device)
    apply_sampling(pipe, a)
    results = run_edit_benchmark(pipe, clf, cases, seeds=a.seeds, steps=a.steps, cfg=a.cfg, sampler=a.sampler,
                                 scales=scales, seed_base=a.seed, progress=lambda m: print(m, flush=True),
                                 suite=a.suite)
    write_results(results, out)
    print(format_report(results))
    print(f"wrote {out / 'results.json'} and {out / 'report.md'}")
    return 0


def add_eval_fidelity(sub) -> None:
    """Register `salad eval-fidelity` on the CLI's subparsers."""
    p = sub.add_parser("eval-fidelity", help="per-class fidelity of held-out paraphrases against real clips")
    p.add_argument("--data", help="labelled HumanML3D-layout dataset (labels.json); required unless --rejudge")
    p.add_argument("--out", help="directory for results.json and report.md; required unless --rejudge")
    p.add_argument("--rejudge", metavar="DIR", nargs="+", default=None,
                   help="judge a stored run (DIR/results.json) again under the current rules from the measures it "
                        "keeps, generating nothing; writes to --out, or back into DIR. With --data, its real "
                        "reference clips are also chosen and measured again (the current reference rule). Several "
                        "DIRs (runs of the same settings with other seeds, e.g. --first-seed 0 and 3) are pooled "
                        "into one table judged on all their seeds; --out is then required")
    p.add_argument("--compare", metavar="DIR[:clean]", nargs="+", default=None,
                   help="stored runs side by side, judged under the current rules: a row per class, a column per "
                        "run's raw table (DIR:clean: its table after the foot lock), a cell the checks that fail; "
                        "prints it as Markdown, and writes it to --out (a .md file) when given")
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--classes", default=None, help="comma list of classes (default: all), e.g. walk,kick")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--first-seed", type=int, default=0,
                   help="the seeds run from this one (default 0); other seeds show how much the table moves by chance")
    p.add_argument("--prompt-set", choices=tuple(PROMPT_SETS), default="a",
                   help="which held-out paraphrase set prompts each class (salad.eval.paraphrases): a (default), or "
                        "b, written later to check that template changes generalise beyond set a's wording")
    p.add_argument("--length", choices=("auto", "model", "prior"), default="auto",
                   help="as generate --seconds: auto (default): the model ends each motion itself, within a band "
                        "around the training data's length for the prompt; model: the model alone; prior: the "
                        "training data's length")
    add_sampling(p)
    p.add_argument("--split", default="test")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    p.add_argument("--classifier", default=str(EMBEDDED_CLASSIFIER),
                   help="classifier that judges which action each generated motion shows (default: the one shipped "
                        "in assets/eval); 'none' skips it")
    add_device(p)
    p.set_defaults(func=cmd_eval_fidelity)


def cmd_eval_fidelity(a) -> int:
    from ..data.labels import read_labels
    from ..eval.classifiers import load_classifier
    from ..eval.fidelity import evaluate_fidelity, fidelity_classes
    from ..pipeline import load_pipeline

    if a.compare:
        if a.rejudge:
            raise ValueError("--compare and --rejudge are separate uses of eval-fidelity; give one")
        return _compare_fidelity(a.compare, Path(a.out) if a.out else None)
    if a.rejudge:
        if len(a.rejudge) > 1 and not a.out:
            raise ValueError("pooling several runs (--rejudge DIR DIR...) needs --out")
        return _rejudge_fidelity([Path(d) for d in a.rejudge], Path(a.out or a.rejudge[0]), a.data)
    if not a.data or not a.out:
        raise ValueError("eval-fidelity needs --data and --out (or --rejudge DIR)")
    device = device_of(a)
    classes = [c.strip() for c in a.classes.split(",") if c.strip()] if a.classes else None
    fidelity_classes(classes, a.prompt_set)                      # unknown names fail before loading anything
    if a.seeds < 1 or a.first_seed < 0:
        raise ValueError(f"--seeds must be at least 1 and --first-seed at least 0, got {a.seeds} and {a.first_seed}")
    read_labels(a.data)
    clf = None
    if a.classifier != "none":
        clf = load_classifier(a.classifier)
        clf.meta["path"] = str(a.classifier)
    pipe = load_pipeline(a.model, bf16=not a.fp32, threads=a.threads or None, device=device)
    apply_sampling(pipe, a)
    bar, update = progress_bar("generating")
    results = evaluate_fidelity(pipe, a.data, seeds=a.seeds, steps=a.steps, cfg=a.cfg, sampler=a.sampler,
                                classes=classes, split=a.split, classifier=clf, progress=update, length=a.length,
                                prompt_set=a.prompt_set, first_seed=a.first_seed)
    bar.close()
    _write_fidelity(results, Path(a.out))
    return 0


def _rejudge_fidelity(sources: list[Path], out: Path, data: str | None) -> int:
    from ..data.labels import read_labels
    from ..eval.fidelity import pool, rejudge
    if data is not None:
        read_labels(data)                         # a dataset that cannot be read says so before anything else
    stored = [_stored_fidelity(src)[0] for src in sources]
    results = rejudge(pool(stored) if len(stored) > 1 else stored[0], data)
    _write_fidelity(results, out)
    return 0


def _stored_fidelity(src: Path) -> tuple[dict, dict]:
    """A stored run's results as stored, and judged again under the current rules."""
    from ..eval.fidelity import rejudge
    try:
        stored = json.loads((src / "results.json").read_text())
        return stored, rejudge(stored)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{src / 'results.json'} is not a readable eval-fidelity result: {e}") from None


def _compare_fidelity(specs: list[str], out: Path | None) -> int:
    from ..eval.fidelity import compare_markdown
    runs = []
    for spec in specs:
        src, _, variant = spec.rpartition(":")
        if variant not in ("raw", "clean"):
            src, variant = spec, "raw"
        runs.append((_stored_fidelity(Path(src))[1], variant))
    table = compare_markdown(runs)
    if out is not None:
        atomic_write_text(out, table)
    print(table, end="")
    return 0


def _write_fidelity(results: dict, out: Path) -> None:
    from ..eval.fidelity import report_markdown
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    report = report_markdown(results)
    atomic_write_text(out / "report.md", report)
    print(report)


def add_eval_length(sub) -> None:
    """Register `salad eval-length` on the CLI's subparsers."""
    p = sub.add_parser("eval-length", help="auto-length generation vs the test set's lengths (JSD, EMD)")
    p.add_argument("--data", required=True, help="HumanML3D-layout dataset")
    p.add_argument("--out", required=True, help="directory for results.json, report.md and lengths.png")
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--split", default="test")
    p.add_argument("--samples", type=int, default=256, help="test captions to generate for")
    p.add_argument("--batch", type=int, default=16, help="captions per sampling run")
    add_sampling(p)
    p.add_argument("--bin-frames", type=int, default=DEFAULT_BIN_FRAMES, help="histogram bin width for the JSD")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    add_device(p)
    p.set_defaults(func=cmd_eval_length)


def cmd_eval_length(a) -> int:
    from ..data.dataset import MotionDataset
    from ..data.labels import read_labels
    from ..eval.length_dist import MIN_FRAMES, evaluate_lengths, write_length_report
    from ..pipeline import load_pipeline

    pipe = load_pipeline(a.model, bf16=not a.fp32, threads=a.threads or None, device=device_of(a))
    apply_sampling(pipe, a)
    ds = MotionDataset(a.data, a.split, min_frames=MIN_FRAMES, max_frames=10 ** 9)
    labels = read_labels(a.data) if (Path(a.data) / "labels.json").is_file() else None
    bar, update = progress_bar("generating")
    results = evaluate_lengths(pipe, ds, samples=a.samples, seed=a.seed, steps=a.steps, cfg=a.cfg,
                               sampler=a.sampler, batch=a.batch, bin_frames=a.bin_frames, labels=labels,
                               progress=update)
    bar.close()
    path = write_length_report(results, a.out)
    print(path.read_text())
    return 0


def add_eval_real_edit(sub) -> None:
    p = sub.add_parser("eval-real-edit", help="inversion fidelity and edit success on real test motions")
    p.add_argument("--data", required=True, help="labelled HumanML3D-layout dataset (labels.json, test.txt)")
    p.add_argument("--classifier", default=str(EMBEDDED_CLASSIFIER),
                   help="motion classifier checkpoint directory (default: the one shipped in assets/eval)")
    p.add_argument("--out", required=True, help="directory for results.json and report.md")
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--clips", type=int, default=10, help="test clips for the fidelity part (0 skips it)")
    p.add_argument("--edit-clips", type=int, default=8, help="test clips per edit task (0 skips them)")
    p.add_argument("--methods", default="ddim,negative,null_text,fixed_point",
                   help="inversion methods for the fidelity part")
    p.add_argument("--edit-methods", default="negative,fixed_point", help="inversion methods for the edits")
    p.add_argument("--sdedit", default=",".join(f"{s:g}" for s in SDEDIT_STRENGTHS),
                   help="SDEdit strengths (fractions of T), comma separated; empty for none")
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--cfg", type=float, default=7.5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--uncorrected", action="store_true", help="also run each edit without per-step corrections")
    p.add_argument("--threads", type=int, default=0)
    add_device(p)
    p.set_defaults(func=cmd_eval_real_edit)


def _csv(text: str, cast=str) -> list:
    try:
        return [cast(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"expected a comma-separated list, got {text!r}") from None


def cmd_eval_real_edit(a) -> int:
    import torch
    from ..eval.real_edit_bench import run_real_edit_bench
    from ..pipeline import load_pipeline
    if a.threads:
        torch.set_num_threads(a.threads)
    pipe = load_pipeline(a.model, device=device_of(a))
    run_real_edit_bench(pipe, a.data, a.classifier, a.out, clips=a.clips, edit_clips=a.edit_clips,
                        methods=_csv(a.methods), edit_methods=_csv(a.edit_methods), steps=a.steps, cfg=a.cfg,
                        strengths=_csv(a.sdedit, float), seed=a.seed, uncorrected=a.uncorrected)
    print((Path(a.out) / "report.md").read_text())
    return 0


def add_eval_vae(sub) -> None:
    p = sub.add_parser("eval-vae", help="VAE reconstruction: pose error and what the decoder does to the feet")
    p.add_argument("--data", required=True, help="labelled HumanML3D-layout dataset (labels.json)")
    p.add_argument("--vae", action="append", default=[],
                   help="VAE checkpoint directory; repeatable (default: the embedded model's)")
    p.add_argument("--split", default="test")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--out", required=True, help="directory for results.json and report.md")
    add_device(p)
    p.set_defaults(func=cmd_eval_vae)


def cmd_eval_vae(a) -> int:
    import torch
    from ..eval.vae_feet import evaluate_vae, write_vae_report
    from ..pipeline import EMBEDDED_MODEL
    device = device_of(a)
    if a.threads:
        torch.set_num_threads(a.threads)
    results = []
    for vae in a.vae or [str(EMBEDDED_MODEL / "vae")]:
        bar, update = progress_bar(f"{Path(vae).name}")
        results.append(evaluate_vae(vae, a.data, split=a.split, seed=a.seed, progress=update, device=device))
        bar.close()
    print(write_vae_report(results, a.out, a.split).read_text())
    return 0


def add_eval_classifier(sub) -> None:
    p = sub.add_parser("eval-classifier", help="the content/style/side classifier on real motions: accuracy per "
                                               "split and what it calls each class")
    p.add_argument("--data", required=True, help="labelled HumanML3D-layout dataset (labels.json)")
    p.add_argument("--classifier", default=str(EMBEDDED_CLASSIFIER),
                   help="classifier checkpoint (default: the one shipped in assets/eval)")
    p.add_argument("--splits", default="train,val,test", help="comma-separated splits")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--out", required=True, help="directory for results.json and report.md")
    p.set_defaults(func=cmd_eval_classifier)


def cmd_eval_classifier(a) -> int:
    import torch
    from ..eval.classifiers import load_classifier
    from ..training.classifier_task import classifier_summary, write_classifier_report
    if a.threads:
        torch.set_num_threads(a.threads)
    splits = [s.strip() for s in _csv(a.splits)]
    if not splits or not set(splits) <= {"train", "val", "test"}:
        raise ValueError(f"--splits takes train, val and/or test, got {a.splits!r}")
    results = {"classifier": shown_path(a.classifier), "data": str(a.data),
               **classifier_summary(load_classifier(a.classifier), a.data, splits)}
    print(write_classifier_report(results, a.out).read_text())
    return 0
