"""`salad edit` (text -> source and edited motion) and `salad edit-real` (a real motion edited by text)."""
from __future__ import annotations

from pathlib import Path

from ..editing.spec import DEFAULT_SELF_INJECT, EDIT_MODES, HOLD_CHOICES, MIRROR_PARTS, EditSpec
from ..files import check_writable_dir
from .common import (add_bvh_units, add_device, add_sampling, apply_sampling, device_of, parse_reweight, print_warnings,
                     progress_bar)


def edit_spec(a, hold: str | None = "auto") -> EditSpec:
    """The edit that `salad edit` and `salad edit-real` arguments describe. `hold` is salad edit's alone:
    real-motion editing holds no parts (the spec's "auto" holds nothing there)."""
    return EditSpec(mode=a.mode, target=a.target, tau=a.tau, reweight=parse_reweight(a.reweight), mirror=a.mirror,
                    self_inject=a.self_inject, hold=hold)


def cmd_edit(a) -> int:
    from ..pipeline import load_pipeline
    from ..render import render_side_by_side
    device = device_of(a)
    spec = edit_spec(a, hold=None if a.hold == "none" else a.hold)
    check_writable_dir(a.output)
    pipe = load_pipeline(a.model, bf16=not a.fp32, device=device)
    apply_sampling(pipe, a)
    bar, update = progress_bar("editing")
    res = pipe.edit(a.source, seed=a.seed, seconds=a.seconds, steps=a.steps, cfg=a.cfg, sampler=a.sampler,
                    progress=update, foot_lock=not a.no_foot_lock, spec=spec)
    bar.close()
    print_warnings(res.source, res.edited)
    if res.params["hold"]:      # "auto" decides per prompt: say what it chose
        print(f"held the {res.params['hold']} body to the source")
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    for name, m in (("source", res.source), ("edited", res.edited)):
        m.save(out / f"{name}.npy")
        m.save(out / f"{name}.bvh", bvh_units=a.bvh_units)
    render_side_by_side([res.source.joints, res.edited.joints], [f"source: {res.source.text}", f"edited ({a.mode})"],
                        out / "side_by_side.mp4")
    print(f"wrote {out}/source.npy|bvh, edited.npy|bvh and side_by_side.mp4")
    return 0


def add_edit(sub) -> None:
    e = sub.add_parser("edit", help="zero-shot edit by attention modulation; writes NPY, BVH and a side-by-side MP4")
    e.add_argument("source", help="source prompt")
    e.add_argument("target", nargs="?", default=None, help="target prompt (swap, refine)")
    e.add_argument("--mode", choices=EDIT_MODES, default="swap")
    e.add_argument("-o", "--output", required=True, help="output directory")
    e.add_argument("--tau", type=float, default=None, help="source maps lead while t >= tau*T (swap default 0.8 = the first 20%% of the steps; refine 0 = all)")
    e.add_argument("--reweight", action="append", metavar="WORD=SCALE", help="scale a word's attention (-3..3)")
    e.add_argument("--mirror", choices=MIRROR_PARTS, default=None)
    e.add_argument("--self-inject", type=float, default=DEFAULT_SELF_INJECT, help="share of steps with source self-attention")
    e.add_argument("--hold", choices=HOLD_CHOICES + ("none",), default="auto",
                   help="body parts that follow the source at every step: lower (root path and legs), upper (spine, "
                        "arms, head), none; auto (default) holds the lower body when re-weighting a word of a prompt "
                        "whose action is done in place")
    e.add_argument("--seconds", default=None, help="length in seconds, 'auto' (default), 'model' or 'prior', as for generate")
    e.add_argument("--seed", type=int, default=0)
    add_sampling(e)
    e.add_argument("--model", default=None)
    e.add_argument("--fp32", action="store_true")
    e.add_argument("--no-foot-lock", action="store_true", help="leave out the foot clean-up (planted feet pinned, legs re-solved by IK)")
    add_device(e)
    add_bvh_units(e)
    e.set_defaults(func=cmd_edit)


def add_edit_real(sub) -> None:
    p = sub.add_parser("edit-real", help="edit a real motion (BVH/NPY) by text: inversion + attention editing")
    p.add_argument("input", help="a .bvh file, or .npy joints (T, 22, 3) / features (T, 263)")
    p.add_argument("--source", required=True, help="a prompt describing the input motion")
    p.add_argument("--target", default=None, help="target prompt (swap, refine)")
    p.add_argument("--mode", default="swap", help="swap, refine, reweight or mirror")
    p.add_argument("-o", "--output", action="append", required=True,
                   help="edited motion: .bvh, .npy, .npz, .mp4, .gif or .png; repeat for several formats")
    p.add_argument("--reconstruction", action="append", default=[],
                   help="also write the unedited reconstruction (the source branch) here; repeatable")
    p.add_argument("--side-by-side", default=None, help="an MP4 of input, reconstruction and edit")
    # Spelled out to keep the CLI free of torch; a test checks it against salad.editing.real.DEFAULT_INVERSION.
    p.add_argument("--inversion", default="negative",
                   help="inversion method: negative (default), fixed_point, null_text or ddim")
    p.add_argument("--no-correct", action="store_true",
                   help="sample without the per-step corrections (the source branch then only approximates the input)")
    p.add_argument("--tau", type=float, default=None, help="share of T led by the source maps (swap: 0.8)")
    p.add_argument("--reweight", action="append", metavar="WORD=SCALE", help="scale a word's attention (-3..3)")
    p.add_argument("--mirror", choices=MIRROR_PARTS, default=None)
    p.add_argument("--self-inject", type=float, default=DEFAULT_SELF_INJECT, help="share of steps with source self-attention")
    add_sampling(p, ("ddim", "consistency"), teacher_options=False)
    p.add_argument("--seed", type=int, default=0, help="the consistency sampler's noise seed (ddim inverts instead)")
    p.add_argument("--trim", action="store_true", help="keep the start of motions longer than the model's canvas")
    p.add_argument("--skeleton", default=None,
                   help="skeleton.json with the training bone lengths (default: found next to the model or its data)")
    p.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    p.add_argument("--bf16", action="store_true", help="run the denoiser in bf16 (faster, less exact inversion)")
    p.add_argument("--no-foot-lock", action="store_true", help="leave out the foot clean-up (planted feet pinned, legs re-solved by IK)")
    add_device(p)
    add_bvh_units(p)
    p.set_defaults(func=cmd_edit_real)


def cmd_edit_real(a) -> int:
    from ..editing.real import (edit_encoded_consistency, edit_inverted, encode, invert_real, measure_reconstruction,
                                read_real)
    from ..motion.motion import check_output_paths
    from ..pipeline import load_pipeline

    device = device_of(a)
    spec = edit_spec(a)
    if a.side_by_side and Path(a.side_by_side).suffix.lower() != ".mp4":
        raise ValueError(f"{a.side_by_side}: unsupported output type for --side-by-side; use .mp4")
    check_output_paths(a.output + a.reconstruction + ([a.side_by_side] if a.side_by_side else []))
    pipe = load_pipeline(a.model, device=device)
    apply_sampling(pipe, a)
    pipe.check_edit(a.source, spec)
    steps, cfg, _, _ = pipe.check_sampling(a.steps, a.cfg, a.sampler)
    from ..diffusion.inversion import METHODS
    if a.inversion not in METHODS:
        raise ValueError(f"--inversion must be one of {', '.join(METHODS)}, got {a.inversion!r}")
    if a.sampler == "consistency":
        real = read_real(pipe, a.input, a.skeleton, trim=a.trim)
        bar, update = progress_bar("editing")
        res = edit_encoded_consistency(pipe, encode(pipe, real), spec, a.source, steps, cfg, a.seed, update,
                                       not a.no_foot_lock)
        timing = f"student edit {res.params['edit_seconds']:.1f} s"
    else:
        bar, update = progress_bar("inverting")
        real, inv = invert_real(pipe, a.input, a.source, method=a.inversion, steps=steps, cfg=cfg, fp32=not a.bf16,
                                bone_lengths=a.skeleton, trim=a.trim, progress=update)
        bar.close()
        bar, update = progress_bar("editing")
        res = edit_inverted(pipe, inv, correct=not a.no_correct, progress=update, foot_lock=not a.no_foot_lock,
                            spec=spec)
        timing = f"inversion {res.params['inversion_seconds']:.1f} s, edit {res.params['edit_seconds']:.1f} s"
    bar.close()
    measure_reconstruction(res, real)
    print_warnings(res.edited)
    notes = [f"{k}={v}" for k, v in real.info.items() if k in ("retargeted", "dropped_frames", "trimmed_from_frames")]
    print(f"{real.source}: {real.frames} frames; reconstruction MPJPE {100 * res.source.info['mpjpe_m']:.2f} cm; "
          f"{timing} ({', '.join(notes)})")
    for path in a.output:
        res.edited.save(path, bvh_units=a.bvh_units)
        print(f"wrote {path}")
    for path in a.reconstruction:
        res.source.save(path, bvh_units=a.bvh_units)
        print(f"wrote {path}")
    if a.side_by_side:
        from ..render import render_side_by_side
        render_side_by_side([real.joints, res.source.joints, res.edited.joints],
                            ["input", "reconstruction", f"edited ({a.mode})"], a.side_by_side)
        print(f"wrote {a.side_by_side}")
    return 0
