"""What several commands share: progress bars, prompt warnings, sampling options, --bvh-units and WORD=SCALE
lists."""
from __future__ import annotations

import argparse
import sys


class LazyBar:
    """A tqdm bar that appears at the first progress report, so an argument error raised
    before any work is printed on a clean line instead of after an empty bar."""

    def __init__(self, desc: str):
        self.desc, self.bar = desc, None

    def update(self, i: int, n: int) -> None:
        if self.bar is None:
            from tqdm import tqdm
            # counted from the first report, or the rate shown first is one step over no time
            self.bar = tqdm(total=n, initial=i, desc=self.desc, leave=False)
        self.bar.total = n
        self.bar.n = i
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def progress_bar(desc: str):
    """(bar, its update function) for a library call's progress=."""
    bar = LazyBar(desc)
    return bar, bar.update


def print_warnings(*motions) -> None:
    """The motions' prompt warnings (salad.models.vocabulary) on stderr, each once."""
    seen = []
    for m in motions:
        for w in m.warnings:
            if w not in seen:
                seen.append(w)
                print(f"warning: {m.text!r}: {w}", file=sys.stderr)


def add_device(parser: argparse.ArgumentParser) -> None:
    """--device, for every command that runs the model."""
    # Spelled out to keep the CLI free of torch; salad.precision.resolve_device reads it.
    parser.add_argument("--device", default="auto",
                        help="where the model runs: auto (default: a CUDA GPU when torch sees one, else the CPU), "
                             "cpu, cuda or cuda:N")


def device_of(a):
    """The command's --device, checked before anything slow: a GPU that is not there fails at once."""
    from ..precision import resolve_device
    return resolve_device(a.device)


# Spelled out to keep the CLI free of torch; a test checks them against salad.diffusion.schedule.SAMPLERS.
SAMPLER_CHOICES = ("ddim", "dpm", "dpm-sde", "consistency")
SAMPLER_HELP = {"ddim": "DDIM, the paper's sampler", "dpm": "DPM-Solver++",
                "dpm-sde": "SDE-DPM-Solver++, fresh noise at each step like DDIM's default, in half its steps",
                "consistency": "the consistency-distilled student: 1-4 steps, one forward each"}


def add_sampling(parser: argparse.ArgumentParser, samplers: tuple[str, ...] = SAMPLER_CHOICES,
                 teacher_options: bool = True) -> None:
    """--steps, --cfg, --sampler and --compile, for every command that samples; with teacher_options also
    --ddim-eta, --cfg-rescale and --cfg-cutoff, --projections and --foot-refine (set on the pipeline with
    apply_sampling)."""
    parser.add_argument("--steps", type=int, default=None,
                        help="denoising steps (default: 50 for ddim and dpm, 25 for dpm-sde, 4 for consistency)")
    parser.add_argument("--cfg", type=float, default=7.5,
                        help="classifier-free guidance scale (the consistency student takes the range it learnt)")
    parser.add_argument("--sampler", choices=samplers, default="ddim",
                        help="; ".join(f"{k}: {SAMPLER_HELP[k]}" for k in samplers))
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile the networks the sampling runs (Pipeline.compile): 16-69 s of "
                             "compiling first, then about a sixth less time per motion on a CPU; worth it for "
                             "batches and evaluations, not for one motion")
    if teacher_options:
        parser.add_argument("--ddim-eta", type=float, default=None,
                            help="fresh noise DDIM adds at each step, 0-1 (default 1; 0: the paper's deterministic "
                                 "DDIM, whose walks slide more)")
        parser.add_argument("--cfg-rescale", type=float, default=None,
                            help="pull guided predictions towards the conditional one's scale, 0-1 (default 0.7; "
                                 "0: plain guidance)")
        parser.add_argument("--cfg-cutoff", type=float, default=None,
                            help="share of the noise levels, from the clean end, sampled without guidance, 0-0.99 "
                                 "(default 0.3: the last 15 of 50 DDIM steps; 0: guidance at every step)")
        parser.add_argument("--projections", type=int, default=None,
                            help="times a generated motion goes through the VAE (decoded, encoded to its mean) "
                                 "before the last decode, with every sampler (default 0: the sampler's latents as "
                                 "they are; guided control and real-motion edits decode without it)")
        parser.add_argument("--foot-refine", type=int, default=None,
                            help="loss evaluations with which a generated motion's latent is refined so that the "
                                 "feet its decoder marks as planted stand still (default 20; 0: none; guided "
                                 "control keeps its targets meanwhile; real-motion edits decode without it)")


def apply_sampling(pipe, a) -> None:
    """The command's --ddim-eta, --cfg-rescale, --cfg-cutoff, --projections, --foot-refine and --compile,
    checked, on the pipeline."""
    pipe.set_sampling(getattr(a, "ddim_eta", None), getattr(a, "cfg_rescale", None), getattr(a, "cfg_cutoff", None))
    if getattr(a, "projections", None) is not None:
        pipe.set_projections(a.projections)
    if getattr(a, "foot_refine", None) is not None:
        pipe.set_foot_refine(a.foot_refine)
    if getattr(a, "compile", False):
        pipe.compile()


def add_bvh_units(parser: argparse.ArgumentParser) -> None:
    """--bvh-units, for every command that can write BVH files."""
    # Spelled out to keep the CLI free of torch; tests check it against salad.motion.bvh_export.UNITS_PER_METRE.
    parser.add_argument("--bvh-units", choices=("cm", "m"), default="cm",
                        help="units of .bvh files: cm (default; Maya and MotionBuilder read them as is, Blender "
                             "with Scale 0.01) or m (Blender at its default scale)")


def parse_reweight(items) -> dict[str, float] | None:
    """["word=scale", ...] -> {word: scale}."""
    out = {}
    for item in items or []:
        word, _, scale = item.rpartition("=")
        try:
            out[word] = float(scale)
        except ValueError:
            raise ValueError(f"--reweight takes WORD=SCALE, got {item!r}") from None
        if not word:
            raise ValueError(f"--reweight takes WORD=SCALE, got {item!r}")
    return out or None
