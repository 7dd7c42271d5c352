"""`salad data`: build datasets, inspect them, write a model's vocabulary."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _split_fractions(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected TRAIN,VAL,TEST fractions such as 0.8,0.05,0.15, got {text!r}")


def cmd_data_build(a) -> int:
    if a.source == "bandai":
        from ..data.build import build_bandai
        bvh_only = [f"--{k.replace('_', '-')}" for k in ("mapping", "mirror", "split", "captions", "allow_uncaptioned")
                    if getattr(a, k) not in (None, False)]
        if bvh_only:
            raise SystemExit(f"{', '.join(bvh_only)}: only for --source bvh")
        report = build_bandai(a.input, a.out, workers=a.workers, seed=a.seed)
    else:
        from ..data.build_bvh import build_bvh
        report = build_bvh(a.input, a.out, mapping=a.mapping or "auto", mirror=a.mirror is not False,
                           workers=a.workers, seed=a.seed, split=a.split or (0.8, 0.05, 0.15),
                           captions=a.captions, allow_uncaptioned=a.allow_uncaptioned)
    print(json.dumps({k: v for k, v in report.items() if k != "skipped"}, indent=2))
    for name, why in report["skipped"].items():
        print(f"skipped {name}: {why}")
    return 0


def cmd_data_stats(a) -> int:
    from ..data.build import dataset_stats
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


def cmd_data_vocabulary(a) -> int:
    from ..models.io import load_denoiser
    from ..models.text import load_text_encoder
    from ..models.vocabulary import VOCABULARY_FILE, Vocabulary, build_vocabulary, save_vocabulary
    model = Path(a.model)
    _, doc = load_denoiser(model / "denoiser")
    kept = None
    if a.index_only:
        path = model / VOCABULARY_FILE
        try:
            kept = Vocabulary.from_json(json.loads(path.read_text(encoding="utf-8")), str(path))
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"--index-only needs the model's vocabulary to keep: {path} ({e})") from None
    vocab = build_vocabulary(a.dir, split=a.split)
    if kept is not None:
        kept.captions = vocab.captions
        vocab = kept
    if vocab.captions:
        print(f"encoding {len(vocab.captions)} captions and fitting the length net to their lengths "
              "(minutes on a CPU)", file=sys.stderr)
    path = save_vocabulary(vocab, load_text_encoder(doc["config"]["text_encoder"]), model)
    print(f"wrote {path}: {len(vocab.actions)} actions, {len(vocab.examples)} example captions, "
          f"{len(vocab.words)} words, {len(vocab.captions)} captions in the length index, "
          f"manner words: {', '.join(vocab.styles) or 'none'}")
    return 0


def cmd_data_bundle(a) -> int:
    from ..config import apply_overrides, load_toml
    from ..training.configs import DenoiserTrainConfig
    from ..training.denoiser_task import DenoiserTask
    from ..training.latent_bundle import write_bundle
    if a.part_mib <= 0 or a.windows < 1:
        raise ValueError(f"--part-mib must be > 0 and --windows >= 1, got {a.part_mib} and {a.windows}")
    cfg = load_toml(DenoiserTrainConfig, a.config)
    apply_overrides(cfg, a)
    if cfg.data.bundle:
        raise ValueError(f"{a.config} trains from a bundle already (data.bundle = {cfg.data.bundle!r})")
    cfg.data.balance = 1.0          # every motion's content is stored; the training run's balance applies then
    if a.threads:
        import torch
        torch.set_num_threads(a.threads)
    out = write_bundle(DenoiserTask(cfg, encode_text=a.text == "features"), a.out, int(a.part_mib * 2 ** 20),
                       windows=a.windows, text=a.text)
    sizes = sorted(f.stat().st_size for f in out.glob("*.safetensors"))
    print(f"wrote {out}: {len(sizes)} parts, the largest {sizes[-1] / 2 ** 20:.1f} MiB, "
          f"{sum(sizes) / 2 ** 20:.1f} MiB in all")
    return 0


def cmd_data_denoised_latents(a) -> int:
    import torch
    from ..data.dataset import MotionDataset
    from ..pipeline import load_pipeline
    from ..training.denoised_latents import build_denoised_latents
    if a.batch < 1 or a.min_frames < 4:
        raise ValueError(f"--batch must be >= 1 and --min-frames >= 4, got {a.batch} and {a.min_frames}")
    if a.threads:
        torch.set_num_threads(a.threads)
    pipe = load_pipeline(a.model)
    data = MotionDataset(a.data, a.split, max_frames=10 ** 9, normalizer=pipe.normalizer)
    out = build_denoised_latents(pipe, data, a.out, a.model, seed=a.seed, batch=a.batch,
                                 student_share=a.student_share if pipe.student is not None else 0.0,
                                 min_frames=a.min_frames)
    print(f"wrote {out}")
    return 0


def add_parser(sub) -> None:
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
    v.add_argument("--index-only", action="store_true",
                   help="keep the model's vocabulary.json (its actions, words and example captions, which the "
                        "warnings' threshold was set on) and write only the caption index of the length prior")
    v.set_defaults(func=cmd_data_vocabulary)
    n = data.add_parser(
        "bundle", help="a denoiser training config's data as VAE latents + text features, in parts of bounded size",
        description="Encodes the training motions of a denoiser config with its VAE (posterior means; a motion longer "
                    "than the canvas as --windows windows) and its captions with its text encoder, and writes them "
                    "in parts of at most --part-mib MiB each. Train from it elsewhere (e.g. on a GPU machine that "
                    "takes transfers of bounded size) with `salad train denoiser --bundle DIR` or data.bundle.")
    n.add_argument("--config", required=True, help="denoiser training config (TOML)")
    n.add_argument("--data", help="override data.root")
    n.add_argument("--vae", help="override vae")
    n.add_argument("--out", required=True, help="output directory")
    n.add_argument("--part-mib", type=float, default=48.0, help="largest part in MiB (default: 48)")
    n.add_argument("--windows", type=int, default=8, help="windows kept per motion longer than the canvas (default: 8)")
    n.add_argument("--text", choices=("features", "tower"), default="features",
                   help="store the captions' token features (default), or their token ids and the text encoder's "
                        "weights cut to them (~21 MB in all; the features are computed where the bundle is read)")
    n.add_argument("--threads", type=int, default=0)
    n.set_defaults(func=cmd_data_bundle)
    d = data.add_parser(
        "denoised-latents", help="training clips' latents noised and denoised again by a model, for a decoder fine-tune",
        description="Each training clip (cut to the longest motion the model makes) of at least --min-frames frames is encoded, noised part of the way and denoised again "
                    "under one of its captions by the model's teacher (DDIM from 15-50%% of T, the pipeline's sampling "
                    "settings) or its consistency student (its last one or two of 4 steps). `salad train vae-san` with "
                    "denoised_latents = FILE then teaches the decoder to show the real clip from such latents.")
    d.add_argument("--model", default="assets/model", help="model directory (default: the embedded one)")
    d.add_argument("--data", default="data/bandai-hml", help="the dataset the model was trained on")
    d.add_argument("--split", default="train")
    d.add_argument("--out", required=True, help="output file (.safetensors)")
    d.add_argument("--student-share", type=float, default=0.5,
                   help="share of clips the student denoises when the model has one (default: 0.5)")
    d.add_argument("--min-frames", type=int, default=64,
                   help="shortest clip used (default: 64, the decoder fine-tune's window)")
    d.add_argument("--batch", type=int, default=48)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--threads", type=int, default=0)
    d.set_defaults(func=cmd_data_denoised_latents)
