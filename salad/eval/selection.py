"""Keeping the best checkpoint of a run by a validation score."""
from __future__ import annotations

import json
from pathlib import Path

from ..checkpoint import CheckpointError, read_checkpoint_config
from ..config import defaults_of, to_dict, training_identity
from ..files import atomic_write_text


def best_score(path: Path, kind: str, cfg) -> float:
    """Validation score stored with the checkpoint at `path`, or -inf when there is none from a run of the
    training config `cfg` (a dataclass): a model left by a run with another config never blocks a new one, and a
    stored config from before a field existed reads as that field's default (training_identity)."""
    try:
        doc = read_checkpoint_config(path, kind)
    except CheckpointError:
        return float("-inf")
    meta = doc.get("meta", {})
    if not isinstance(meta.get("train_config"), dict) or (
            training_identity(meta["train_config"], defaults_of(cfg))
            != training_identity(json.loads(json.dumps(to_dict(cfg))))):
        return float("-inf")
    return float(meta.get("val", {}).get("score", float("-inf")))


def log_validation(run_dir: Path, record: dict) -> None:
    """Appends record (which has a "step") to run_dir/val.jsonl, dropping rows of that step or later: a run
    resumed from an earlier checkpoint judges those steps again, and the log keeps one row per step."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / "val.jsonl"
    step, rows = record.get("step"), []
    if path.exists():
        for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                earlier = json.loads(line).get("step")
            except (json.JSONDecodeError, AttributeError):     # a row torn by a kill
                continue
            if not (isinstance(step, int) and isinstance(earlier, int) and earlier >= step):
                rows.append(line)
    atomic_write_text(path, "".join(r + "\n" for r in rows + [json.dumps(record)]))
