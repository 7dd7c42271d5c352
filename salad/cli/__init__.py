"""The `salad` command: one module per command group, each with its `add_parser` and `cmd_*`
functions; the library below holds no argparse code."""
from __future__ import annotations

import argparse
import gc
import sys

from ..environment import use_offline_defaults
from . import bench, control, data, edit, eval, generate, train


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="salad", description="Skeleton-aware latent diffusion for text-driven motion.")
    sub = p.add_subparsers(dest="command", required=True)
    # in the order `salad --help` has always listed them
    for add in (data.add_parser, generate.add_parser, edit.add_edit, bench.add_parser, eval.add_eval,
                train.add_parser, control.add_parser, edit.add_edit_real, eval.add_eval_control, eval.add_eval_edit,
                eval.add_eval_fidelity, eval.add_eval_length, eval.add_eval_real_edit, eval.add_eval_vae,
                eval.add_eval_classifier, train.add_average_parser):
        add(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    use_offline_defaults()
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError, RuntimeError) as e:
        print(f"salad: error: {e}", file=sys.stderr)
        return 2


def run() -> None:
    """The `salad` console command: main(), then exit without the interpreter's last garbage collections."""
    code = main()
    # At exit CPython collects over every object the imported libraries made (torch, transformers, diffusers,
    # scipy): 0.9-1.2 s of a 7.5 s `salad generate -o x.mp4` on this CPU. Frozen objects are left out; outputs
    # are written and closed by now, and atexit handlers (render workers, training's process group) still run.
    gc.freeze()
    sys.exit(code)
