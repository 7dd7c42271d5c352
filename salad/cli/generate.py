"""`salad generate`: text -> motion files."""
from __future__ import annotations

from .common import add_bvh_units, add_device, add_sampling, apply_sampling, device_of, print_warnings, progress_bar


def cmd_generate(a) -> int:
    from ..motion.motion import check_output_paths
    from ..pipeline import load_pipeline
    outs = check_output_paths(a.output)
    pipe = load_pipeline(a.model, bf16=not a.fp32, device=device_of(a))
    apply_sampling(pipe, a)
    bar, update = progress_bar("sampling")
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


def add_parser(sub) -> None:
    g = sub.add_parser("generate", help="text -> motion, saved as .npy/.npz/.bvh/.mp4/.gif/.png")
    g.add_argument("prompt")
    g.add_argument("-o", "--output", action="append", required=True,
                   help="output file; repeat for several formats (e.g. -o walk.mp4 -o walk.bvh)")
    g.add_argument("--seconds", default=None, help="length in seconds; 'auto' (default): the model decides (its activation channel ends "
                        "the motion) within a band around the training data's length for such prompts; 'model': the "
                        "model alone; 'prior': the length the training data gives such prompts (the length prior)")
    g.add_argument("--seed", type=int, default=0)
    add_sampling(g)
    g.add_argument("--batch", type=int, default=1, help="motions to generate (files get a _k suffix)")
    g.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    g.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    g.add_argument("--no-foot-lock", action="store_true", help="leave out the foot clean-up (planted feet pinned, legs re-solved by IK)")
    add_device(g)
    add_bvh_units(g)
    g.set_defaults(func=cmd_generate)
