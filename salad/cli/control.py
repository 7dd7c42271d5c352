"""`salad control`: text -> motion that follows a path, keyframes, target positions or a lower body."""
from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

from ..editing.spec import MIRROR_PARTS, EditSpec
from .common import add_bvh_units, add_device, add_sampling, apply_sampling, device_of, print_warnings, progress_bar

if TYPE_CHECKING:
    from ..motion.control import ControlSignal

DEFAULT_PATH_SECONDS = 5.0
# Spelled out to keep the CLI free of torch; a test checks them against salad.motion.control.PATH_PRESETS.
PATH_PRESETS = ("line", "circle", "s-curve", "turn-left", "turn-right")
SOURCES = ("path", "path_preset", "mola", "targets", "keyframes", "lower_body_from")


def add_parser(sub) -> argparse.ArgumentParser:
    """Register `control` on the CLI's subparsers."""
    c = sub.add_parser("control", help="guided generation: follow a pelvis path, keyframes, targets or a lower body")
    c.add_argument("prompt")
    src = c.add_mutually_exclusive_group(required=True)
    src.add_argument("--path", metavar="X,Z;X,Z;...", help="pelvis path through these ground points (metres; "
                                                            "+Z is forward, +X the character's left)")
    src.add_argument("--path-preset", choices=PATH_PRESETS, help="a ready-made pelvis path")
    src.add_argument("--mola", metavar="FILE.npy", help="MoLA control file: (T, 22, 3) positions, all-zero joints free")
    src.add_argument("--targets", metavar="FILE", help="(T, 22, 3) .npy with NaN for free entries, or .npz with "
                                                       "'targets' and a boolean 'mask'")
    src.add_argument("--keyframes", metavar="FILE.npz", help="in-betweening: 'frames' (K,) and 'poses' (K, 22, 3)")
    src.add_argument("--lower-body-from", metavar="MOTION", help="keep this motion's lower body (.npy/.npz/.bvh) "
                                                                 "and generate the upper body")
    c.add_argument("-o", "--output", action="append", required=True,
                   help="output file (.npy/.npz/.bvh/.mp4/.gif/.png); repeat for several formats")
    c.add_argument("--seconds", type=float, default=None,
                   help=f"length; paths default to {DEFAULT_PATH_SECONDS:g} s, files to their own length "
                        "(a shorter --seconds uses their first part)")
    c.add_argument("--speed", type=float, default=1.0, help="walking speed along --path-preset, m/s")
    c.add_argument("--height", type=float, default=None, help="also hold the pelvis at this height along a path (m)")
    c.add_argument("--strength", type=float, default=1.0, help="guidance strength (0 = none)")
    add_sampling(c, ("ddim", "consistency"), teacher_options=False)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--repeats", type=int, default=None, help="time-travel repeats per step (default: 1-3 by phase)")
    c.add_argument("--gradient-steps", type=int, default=None, help="guidance steps per network evaluation")
    c.add_argument("--refine-steps", type=int, default=None, help="guidance steps on the final latent")
    c.add_argument("--mirror", choices=MIRROR_PARTS, default=None,
                   help="also mirror these limbs by attention editing; the unedited motion is written next to each "
                        "output with a _source suffix")
    c.add_argument("--model", default=None, help="model directory (default: the embedded model)")
    c.add_argument("--fp32", action="store_true", help="disable bf16 autocast")
    c.add_argument("--no-foot-lock", action="store_true", help="leave out the foot clean-up (planted feet pinned, legs re-solved by IK)")
    add_device(c)
    add_bvh_units(c)
    c.set_defaults(func=cmd_control)
    return c


def _frames(seconds: float | None, default: float | None = None) -> int | None:
    from ..motion.representation import FPS
    s = default if seconds is None else seconds
    if s is None:
        return None
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"--seconds must be a positive number, got {seconds!r}")
    return max(4, int(round(s * FPS / 4)) * 4)


def signal_from_args(a) -> ControlSignal:
    """The control signal the arguments describe (validated; no model needed)."""
    from ..motion.control import (crop_signal, lower_body_signal, parse_points, path_signal, preset_path,
                                  read_keyframes, read_mola_control, read_motion_joints, read_targets)
    from ..motion.representation import FPS
    given = [k for k in SOURCES if getattr(a, k, None) is not None]
    if len(given) != 1:
        raise ValueError("give exactly one of --path, --path-preset, --mola, --targets, --keyframes, --lower-body-from")
    if a.path is not None or a.path_preset is not None:
        frames = _frames(a.seconds, DEFAULT_PATH_SECONDS)
        if a.path_preset is not None:
            return preset_path(a.path_preset, frames, speed=a.speed, height=a.height)
        return path_signal(parse_points(a.path), frames, height=a.height)
    frames = _frames(a.seconds)
    if a.keyframes is not None:
        return read_keyframes(a.keyframes, frames)
    if a.mola is not None:
        sig = read_mola_control(a.mola)
    elif a.targets is not None:
        sig = read_targets(a.targets)
    else:
        sig = lower_body_signal(read_motion_joints(a.lower_body_from))
    if frames is not None:
        if frames > sig.frames:
            raise ValueError(f"--seconds {a.seconds:g} asks for {frames} frames but the control file has only "
                             f"{sig.frames} ({sig.frames / FPS:g} s)")
        sig = crop_signal(sig, frames)
    return sig


def _error_line(m, sig: ControlSignal) -> str:
    from ..motion.control import control_errors
    e = control_errors(m.joints, sig)
    return (f"control error: mean {e.mean() * 100:.1f} cm, max {e.max() * 100:.1f} cm over {e.size} constrained "
            f"joint-frames")


def cmd_control(a) -> int:
    from ..motion.motion import check_output_paths
    from ..motion.representation import FPS
    from ..pipeline import load_pipeline

    device = device_of(a)
    sig = signal_from_args(a)
    outs = check_output_paths(a.output)
    if a.path is not None and abs(sig.targets[0, 0, 0]) + abs(sig.targets[0, 0, 2]) > 0.05:
        print("note: generated motions start at the origin; this path starts "
              f"{math.hypot(sig.targets[0, 0, 0], sig.targets[0, 0, 2]):.2f} m away from it")
    pipe = load_pipeline(a.model, bf16=not a.fp32, device=device)
    apply_sampling(pipe, a)
    if sig.frames > pipe.canvas_frames:
        raise ValueError(f"the control signal spans {sig.frames} frames ({sig.frames / FPS:g} s); the model makes at "
                         f"most {pipe.canvas_frames} ({pipe.max_seconds:g} s): pass a shorter --seconds")
    bar, update = progress_bar("guided sampling")
    res = pipe.control(a.prompt, signal=sig, seed=a.seed, strength=a.strength, steps=a.steps, cfg=a.cfg,
                       sampler=a.sampler,
                       repeats=a.repeats, gradient_steps=a.gradient_steps, refine_steps=a.refine_steps,
                       progress=update, foot_lock=not a.no_foot_lock,
                       edit=None if a.mirror is None else EditSpec(mode="mirror", mirror=a.mirror))
    bar.close()
    motions = [("", res)] if a.mirror is None else [("", res.edited), ("_source", res.source)]
    print_warnings(*(m for _, m in motions))
    for suffix, m in motions:
        for o in outs:
            path = o.with_name(f"{o.stem}{suffix}{o.suffix}")
            m.save(path, bvh_units=a.bvh_units)
            print(f"wrote {path} ({m.frames} frames, {m.seconds:.2f} s)")
        print(("source " if suffix else "") + _error_line(m, sig))
    return 0
