"""`salad bench`: generation speed, solver accuracy and where the time goes."""
from __future__ import annotations

from pathlib import Path


def report_path(out: str) -> Path:
    """--out as the report file: a directory (one that exists, or a name without .json), as the eval
    commands take, gets bench.json inside it; a .json name is the file itself."""
    path = Path(out)
    return path if path.suffix == ".json" and not path.is_dir() else path / "bench.json"


def cmd_bench(a) -> int:
    from ..bench import bench, format_table
    from ..checkpoint import read_checkpoint_config
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
    out = report_path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    report = bench(out, models=models, batches=batches, quick=a.quick)
    print(format_table(report))
    print(f"\nwrote {out}")
    return 0


def add_parser(sub) -> None:
    bn = sub.add_parser("bench", help="measure generation speed, solver accuracy and where the time goes")
    bn.add_argument("--out", default="bench.json",
                    help="the report: a .json file, or a directory to write bench.json in")
    bn.add_argument("--models", default="embedded,paper", help="comma list: embedded, paper, or a model dir")
    bn.add_argument("--batches", default="1,16")
    bn.add_argument("--quick", action="store_true", help="one repeat per setting")
    bn.set_defaults(func=cmd_bench)
