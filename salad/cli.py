"""The `salad` command line."""
from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
from pathlib import Path

from .eval import EMBEDDED_EVALUATOR

PLUGIN_COMMANDS = ("salad.control_cli", "salad.editing.real", "salad.eval.control_bench", "salad.eval.edit_bench",
                   "salad.eval.fidelity", "salad.eval.length_dist", "salad.eval.real_edit_bench")


def _env_defaults() -> None:
    # Never reach for a model hub or send telemetry: everything here runs offline.
    for k, v in (("HF_HUB_OFFLINE", "1"), ("HF_HUB_DISABLE_TELEMETRY", "1"), ("TRANSFORMERS_OFFLINE", "1"),
                 ("GRADIO_ANALYTICS_ENABLED", "False")):
        os.environ.setdefault(k, v)


def _split_fractions(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected TRAIN,VAL,TEST fractions such as 0.8,0.05,0.15, got {text!r}")


def cmd_data_build(a) -> int:
    if a.source == "bandai":
        from .data.build import build_bandai
        bvh_only = [f"--{k.replace('_', '-')}" for k in ("mapping", "mirror", "split", "captions", "allow_uncaptioned")
                    if getattr(a, k) not in (None, False)]
        if bvh_only:
            raise SystemExit(f"{', '.join(bvh_only)}: only for --source bvh")
        report = build_bandai(a.input, a.out, workers=a.workers, seed=a.seed)
    else:
        from .data.build_bvh import build_bvh
        report = build_bvh(a.input, a.out, mapping=a.mapping or "auto", mirror=a.mirror is not False,
                           workers=a.workers, seed=a.seed, split=a.split or (0.8, 0.05, 0.15),
                           captions=a.captions, allow_uncaptioned=a.allow_uncaptioned)
    print(json.dumps({k: v for k, v in report.items() if k != "skipped"}, indent=2))
    for name, why in report["skipped"].items():
        print(f"skipped {name}: {why}")
    return 0


def cmd_data_stats(a) -> int:
    from .data.build import dataset_stats
    s = dataset_stats(a.dir)
    if a.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"{a.dir}: {s['motions']} motions, {s['hours']:.2f} hours")
    for title, key in (("split", "per_split"), ("content", "per_content"), ("style", "per_style"),
                       ("length", "length_histogram")):
        if s[key]:
            print(f"\nper {title}:")
            for k, v in (sorted(s[key].items()) if key != "length_histogram" else s[key].items()):
                print(f"  {k:24s} {v:6d}")
    if s["length_seconds"]:
        print("\nlength (s): " + ", ".join(f"{k} {v:.2f}" for k, v in s["length_seconds"].items()))
    return 0


class _LazyBar:
    """A tqdm bar that appears at the first progress report, so an argument error raised
    before any work is printed on a clean line instead of after an empty bar."""

    def __init__(self, desc: str):
        self.desc, self.bar = desc, None

    def update(self, i: int, n: int) -> None:
        if self.bar is None:
            from tqdm import tqdm
            self.bar = tqdm(total=n, desc=self.desc, leave=False)
        self.bar.total = n
        self.bar.n = i
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def add_bvh_units(parser: argparse.ArgumentParser) -> None:
    """--bvh-units, for every command that can write BVH files."""
    # Spelled out to keep this module free of torch; tests check it against salad.motion.bvh_export.UNITS_PER_METRE.
    parser.add_argument("--bvh-units", choices=("cm", "m"), default="cm",
                        help="units of .bvh files: cm (default; Maya and MotionBuilder read them as is, Blender "
                             "with Scale 0.01) or m (Blender at its default scale)")


def _progress_bar(desc: str):
    bar = _LazyBar(desc)
    return bar, bar.update


def print_warnings(*motions) -> None:
    """The motions' prompt warnings (salad.models.vocabulary) on stderr, each once."""
    seen = []
    for m in motions:
        for w in m.warnings:
            if w not in seen:
                seen.append(w)
                print(f"warning: {m.text!r}: {w}", file=sys.stderr)


def cmd_data_vocabulary(a) -> int:
    from .models.io import load_denoiser
    from .models.text import load_text_encoder
    from .models.vocabulary import build_vocabulary, save_vocabulary
    model = Path(a.model)
    _, doc = load_denoiser(model / "denoiser")
    vocab = build_vocabulary(a.dir, split=a.split)
    path = save_vocabulary(vocab, load_text_encoder(doc["config"]["text_encoder"]), model)
    print(f"wrote {path}: {len(vocab.actions)} actions, {len(vocab.examples)} example captions, "
          f"{len(vocab.words)} words, manner words: {', '.join(vocab.styles) or 'none'}")
    return 0


def cmd_generate(a) -> int:
    from .motion.motion import check_output_paths
    from .pipeline import load_pipeline
    outs = check_output_paths(a.output)
    pipe = load_pipeline(a.model, bf16=not a.fp32)
    bar, update = _progress_bar("sampling")
    motions = pipe.generate(a.prompt, seconds=a.seconds, seed=a.seed, steps=a.steps, cfg=a.cfg, sampler=a.sampler,
                            batch=a.batch, progress=update, foot_lock=not a.no_foot_lock)
    bar.close()
    motions = motions if isinstance(motions, list) else [motions]
    print_warnings(*motions)
    for k, m in enumerate(motions):
        for o in outs:
            path = o if len(motions) == 1 else o.with_name(f"{o.stem}_{k}{o.suffix}")
            m.save(path, bvh_units=a.bvh_units)
            print(f"wrote {path} ({m.frames} frames, {m.seconds:.2f} s)")
    return 0


def cmd_edit(a) -> int:
    from .pipeline import load_pipeline
    from .render import render_side_by_side
    pipe = load_pipeline(a.model, bf16=not a.fp32)
    reweight = {}
    for item in a.reweight or []:
        word, _, scale = item.rpartition("=")
        try:
            reweight[word] = float(scale)
        except ValueError:
            raise ValueError(f"--reweight takes WORD=SCALE, got {item!r}") from None
    bar, update = _progress_bar("editing")
    res = pipe.edit(a.source, a.target, mode=a.mode, seed=a.seed, seconds=a.seconds, steps=a.steps, cfg=a.cfg,
                    sampler=a.sampler, tau=a.tau, reweight=reweight or None, mirror=a.mirror,
                    self_inject=a.self_inject, progress=update, foot_lock=not a.no_foot_lock)
    bar.close()
    print_warnings(res.source, res.edited)
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    for name, m in (("source", res.source), ("edited", res.edited)):
        m.save(out / f"{name}.npy")
        m.save(out / f"{name}.bvh", bvh_units=a.bvh_units)
    render_side_by_side([res.source.joints, res.edited.joints], [f"source: {res.source.text}", f"edited ({a.mode})"],
                        out / "side_by_side.mp4")
    print(f"wrote {out}/source.npy|bvh, edited.npy|bvh and side_by_side.mp4")
    return 0


def cmd_bench(a) -> int:
    from .bench import bench, format_table
    from .checkpoint import read_checkpoint_config
    models = tuple(m.strip() for m in a.models.split(",") if m.strip())
    if not models:
        raise ValueError("--models is empty")
    for m in models:     # checked now, not after minutes of benchmarking the others
        if m not in ("embedded", "paper"):
            if not Path(m).is_dir():
                raise ValueError(f"--models: {m!r} is neither 'embedded', 'paper' nor a model directory")
            read_checkpoint_config(Path(m) / "vae", "vae")
            read_checkpoint_config(Path(m) / "denoiser", "denoiser")
    try:
        batches = tuple(int(b) for b in a.batches.split(","))
    except ValueError:
        raise ValueError(f"--batches takes a comma list of batch sizes, got {a.batches!r}") from None
    if not batches or min(batches) < 1:
        raise ValueError(f"--batches: batch sizes must be >= 1, got {a.batches!r}")
    report = bench(Path(a.out), models=models, batches=batches, quick=a.quick)
    print(format_table(report))
    print(f"\nwrote {a.out}")
    return 0


def cmd_eval(a) -> int:
    import torch
    from .data.dataset import MotionDataset
    from .eval.evaluator import load_evaluator
    from .eval.generators import ModelGenerator, VAEReconstruction
    from .eval.t2m import evaluate_t2m, ground_truth_generator, write_report
    from .pipeline import load_pipeline
    if a.threads:
        torch.set_num_threads(a.threads)
    ev = load_evaluator(a.evaluator)
    ds = MotionDataset(a.data, a.split, max_frames=10 ** 9)
    partial = Path(a.out) / "partial"      # finished repeats, so that a rerun resumes
    rows = {"Real motion": evaluate_t2m(ground_truth_generator(ds), ds, ev, repeats=a.repeats, seed=a.seed,
                                        progress=True)}
    for model in [] if a.real_only else a.model or [None]:
        pipe = load_pipeline(model, bf16=not a.fp32)
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


def cmd_train(a) -> int:
    from .config import apply_overrides, load_toml
    from .training.configs import DenoiserTrainConfig, VAETrainConfig
    from .training.loop import Trainer
    if a.continue_from and a.what not in ("vae", "denoiser"):
        raise ValueError(f"--continue-from applies to the vae and the denoiser, not to {a.what}")
    if a.init_from and a.what not in ("vae", "vae-san", "denoiser"):
        raise ValueError(f"--init-from applies to the vae, vae-san and the denoiser, not to {a.what}")
    if a.what == "vae":
        from .training.vae_task import VAETask
        cfg = load_toml(VAETrainConfig, a.config)
        apply_overrides(cfg, a)
        task, ema = VAETask(cfg), None
    elif a.what == "denoiser":
        from .training.denoiser_task import DenoiserTask
        cfg = load_toml(DenoiserTrainConfig, a.config)
        apply_overrides(cfg, a)
        task, ema = DenoiserTask(cfg), cfg.ema_decay
    elif a.what == "vae-san":
        from .training.vae_adv_task import train_vae_san
        return train_vae_san(a)
    elif a.what == "classifier":
        from .eval.train_classifier import train_classifier
        return train_classifier(a)
    else:
        from .eval.train_evaluator import train_evaluator
        return train_evaluator(a)
    trainer = Trainer(task, cfg.optim, cfg.run, ema_decay=ema)
    if a.init_from or a.continue_from:
        trainer.init_weights(a.init_from or a.continue_from, carry_step=bool(a.continue_from))
    out = trainer.fit()
    print(f"model written to {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="salad", description="Skeleton-aware latent diffusion for text-driven motion.")
    sub = p.add_subparsers(dest="command", required=True)

    data = sub.add_parser("data", help="build and inspect datasets").add_subparsers(dest="data_cmd", required=True)
    b = data.add_parser(
        "build", help="build a HumanML3D-format dataset from labelled mocap",
        description="--source bandai: the Bandai-Namco research motion archive, captions made from its labels. "
                    "--source bvh: every *.bvh under a folder; a clip's captions come from <clip>.txt next to it "
                    "(one per line) or from captions.json at the folder's root ({\"path/clip.bvh\": [\"a person "
                    "...\"]}); a caption is plain text or a HumanML3D line caption#tokens#start#end.")
    b.add_argument("--source", choices=("bandai", "bvh"), default="bandai", help="dataset kind (default: bandai)")
    b.add_argument("--input", required=True,
                   help="bandai: the archive (.tar.xz) or its unpacked folder; bvh: a folder of .bvh files")
    b.add_argument("--out", required=True, help="output directory")
    b.add_argument("--workers", type=int, default=2)
    b.add_argument("--seed", type=int, default=0, help="random seed of the train/val/test split")
    b.add_argument("--mapping", default=None,
                   help="bvh: joint names: auto (default: detect), bandai, salad, smpl, mixamo, or FILE.json "
                        "{\"pelvis\": \"Hips\", ...} naming the source joint of each of the 22 joints")
    b.add_argument("--mirror", action=argparse.BooleanOptionalAction, default=None,
                   help="bvh: also store mirrored copies (M<id>) with left/right swapped in the captions "
                        "(default: on)")
    b.add_argument("--split", type=_split_fractions, default=None, metavar="TRAIN,VAL,TEST",
                   help="bvh: split fractions (default: 0.8,0.05,0.15)")
    b.add_argument("--captions", default=None,
                   help="bvh: captions JSON keyed by path relative to --input (default: captions.json in --input)")
    b.add_argument("--allow-uncaptioned", action="store_true",
                   help="bvh: keep clips without captions (for VAE training) instead of skipping them")
    b.set_defaults(func=cmd_data_build)
    s = data.add_parser("stats", help="counts per content, style and split, and lengths")
    s.add_argument("dir")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_data_stats)
    v = data.add_parser("vocabulary", help="what a model knows: its trained actions and words, for prompt warnings",
                        description="Writes vocabulary.json (+ the captions' text features) into a model directory "
                                    "from the dataset its denoiser was trained on; generation then warns about "
                                    "prompts outside it.")
    v.add_argument("dir", help="the dataset (HumanML3D layout; labels.json gives the action of each motion)")
    v.add_argument("--model", default="assets/model", help="model directory holding denoiser/ (default: the embedded one)")
    v.add_argument("--split", default="train")
    v.set_defaults(func=cmd_data_vocabulary)

    g = sub.add_parser("generate", help="text -> motion, saved as .npy/.npz/.bvh/.mp4/.gif/.png")
    g.add_argument("prompt")
    g.add_argument("-o", "--output", action="append", required=True,
                   help="output file; repeat for several formats (e.g. -o walk.mp4 -o walk.bvh)")
    g.add_argument("--seconds", default=None, help="length in seconds, or 'auto' (default) to let the model decide")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--steps", type=int, default=50)
    g.add_argument("--cfg", type=float, default=7.5, help="classifier-free guidance scale")
    g.add_argument("--sampler", choices=("ddim", "dpm"), default="ddim")
    g.add_argument("--batch", type=int, default=1, help="motions to generate (files get a _k suffix)")
    g.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    g.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    g.add_argument("--no-foot-lock", action="store_true", help="leave out the foot clean-up (planted feet pinned, legs re-solved by IK)")
    add_bvh_units(g)
    g.set_defaults(func=cmd_generate)

    e = sub.add_parser("edit", help="zero-shot edit by attention modulation; writes NPY, BVH and a side-by-side MP4")
    e.add_argument("source", help="source prompt")
    e.add_argument("target", nargs="?", default=None, help="target prompt (swap, refine)")
    e.add_argument("--mode", choices=("swap", "refine", "reweight", "mirror"), default="swap")
    e.add_argument("-o", "--output", required=True, help="output directory")
    e.add_argument("--tau", type=float, default=None, help="source maps lead while t >= tau*T (swap default 0.8 = the first 20%% of the steps; refine 0 = all)")
    e.add_argument("--reweight", action="append", metavar="WORD=SCALE", help="scale a word's attention (-3..3)")
    e.add_argument("--mirror", choices=("lower", "upper", "all"), default=None)
    e.add_argument("--self-inject", type=float, default=0.2, help="share of steps with source self-attention")
    e.add_argument("--seconds", default=None)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--steps", type=int, default=50)
    e.add_argument("--cfg", type=float, default=7.5)
    e.add_argument("--sampler", choices=("ddim", "dpm"), default="ddim")
    e.add_argument("--model", default=None)
    e.add_argument("--fp32", action="store_true")
    e.add_argument("--no-foot-lock", action="store_true", help="leave out the foot clean-up (planted feet pinned, legs re-solved by IK)")
    add_bvh_units(e)
    e.set_defaults(func=cmd_edit)

    bn = sub.add_parser("bench", help="measure generation speed, solver accuracy and where the time goes")
    bn.add_argument("--out", default="bench.json")
    bn.add_argument("--models", default="embedded,paper", help="comma list: embedded, paper, or a model dir")
    bn.add_argument("--batches", default="1,16")
    bn.add_argument("--quick", action="store_true", help="one repeat per setting")
    bn.set_defaults(func=cmd_bench)

    ev = sub.add_parser("eval", help="T2M protocol: FID, R-precision, MM-Dist, Diversity, MultiModality")
    ev.add_argument("--evaluator", default=str(EMBEDDED_EVALUATOR),
                    help="evaluator checkpoint directory (default: the one shipped in assets/eval)")
    ev.add_argument("--data", required=True, help="HumanML3D-layout dataset")
    ev.add_argument("--model", action="append", help="model directory (default: the embedded model); repeatable")
    ev.add_argument("--real-only", action="store_true", help="score only the real motions (the reference row)")
    ev.add_argument("--split", default="test")
    ev.add_argument("--repeats", type=int, default=20)
    ev.add_argument("--steps", type=int, default=50)
    ev.add_argument("--sampler", choices=("ddim", "dpm"), default="ddim")
    ev.add_argument("--cfg", type=float, default=7.5)
    ev.add_argument("--mm-prompts", type=int, default=32)
    ev.add_argument("--mm-repeats", type=int, default=10)
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--threads", type=int, default=0)
    ev.add_argument("--fp32", action="store_true",
                    help="disable bf16 autocast (CPUs without bf16 run fp32 anyway); a run resumes only in the precision it started in")
    ev.add_argument("--out", required=True, help="directory for results.json and report.md")
    ev.set_defaults(func=cmd_eval)

    t = sub.add_parser("train", help="train the VAE, the denoiser, the evaluator or the classifier",
                       epilog="--init-from and --continue-from are ignored when the run's out_dir holds a saved "
                              "state: the run resumes from it.")
    t.add_argument("what", choices=("vae", "vae-san", "denoiser", "evaluator", "classifier"))
    t.add_argument("--config", required=True, help="TOML config file")
    t.add_argument("--out-dir", help="override run.out_dir")
    t.add_argument("--data", help="override data.root")
    t.add_argument("--max-steps", type=int, help="override optim.max_steps")
    t.add_argument("--threads", type=int, help="override run.threads (CPU threads for this process)")
    t.add_argument("--device", help="override run.device: auto (default: a CUDA GPU when torch sees one, else the "
                                    "CPU), cpu, cuda or cuda:N; under torchrun each process takes its LOCAL_RANK's GPU")
    t.add_argument("--vae", help="denoiser: override vae (the VAE whose latents it learns), e.g. assets/model/vae")
    start = t.add_mutually_exclusive_group()
    start.add_argument("--init-from", metavar="MODEL_DIR",
                       help="fine-tune: start a new run (step 0) from an exported model's weights")
    start.add_argument("--continue-from", metavar="MODEL_DIR",
                       help="train an exported model further: its weights and step count, so the LR schedule and "
                            "max_steps count on from its step; the fresh optimiser warms up again over warmup_steps")
    t.set_defaults(func=cmd_train)

    # benchmarks and tools that register their own subcommand next to their implementation
    for name in PLUGIN_COMMANDS:
        importlib.import_module(name).add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    _env_defaults()
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:
        return 130
    except (ValueError, FileNotFoundError, RuntimeError) as e:
        print(f"salad: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
