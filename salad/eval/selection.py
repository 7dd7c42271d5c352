"""Keeping the best checkpoint of a run by a validation score."""
from __future__ import annotations

import json
from pathlib import Path

from ..checkpoint import CheckpointError, read_checkpoint_config
from ..config import training_identity


def best_score(path: Path, kind: str, config: dict) -> float:
    """Validation score stored with the checkpoint at `path`, or -inf when there is none from this config
    (a model left by a run with another config never blocks a new one)."""
    try:
        doc = read_checkpoint_config(path, kind)
    except CheckpointError:
        return float("-inf")
    meta = doc.get("meta", {})
    if not isinstance(meta.get("train_config"), dict) or (
            training_identity(meta["train_config"]) != training_identity(json.loads(json.dumps(config)))):
        return float("-inf")
    return float(meta.get("val", {}).get("score", float("-inf")))


def log_validation(run_dir: Path, record: dict) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "val.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")
