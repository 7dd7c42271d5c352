"""Weight averaging: one denoiser (or consistency student) whose every weight is the weighted mean of
the same weight in several checkpoints.

This only makes sense for fine-tunes of one start (e.g. students trained on from one student with
different adversarial weights), whose weights still lie in one basin; the checks below can refuse
checkpoints that cannot correspond, not ones that merely diverged too far."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import torch

from ..checkpoint import load_checkpoint, save_checkpoint
from ..config import training_identity

# what a student's meta.consistency records that all averaged students must share: the teacher,
# the guidance range and grid they learnt; default_for is a measurement, which no average inherits
_SHARED_CONSISTENCY = ("teacher", "guidance", "grid_steps", "cfg_rescale", "cfg_cutoff")


def average_checkpoints(paths: Sequence[str | Path], weights: Sequence[float] | None, out: str | Path) -> Path:
    """Write to `out` the checkpoint whose weights are sum_i weights[i] * (paths[i]'s weights);
    weights=None weighs the checkpoints equally."""
    if len(paths) < 2:
        raise ValueError("averaging needs at least two checkpoints")
    if weights is None:
        weights = [1.0 / len(paths)] * len(paths)
    if len(weights) != len(paths):
        raise ValueError(f"{len(paths)} checkpoints but {len(weights)} weights: give one weight per checkpoint")
    if any(not 0.0 <= w <= 1.0 for w in weights) or abs(sum(weights) - 1.0) > 1e-6:
        raise ValueError(f"weights must lie in [0, 1] and sum to 1, got {list(weights)}")
    if any(Path(p).resolve() == Path(out).resolve() for p in paths):
        raise ValueError(f"the output {out} is one of the checkpoints averaged: write the average elsewhere")
    loaded = [load_checkpoint(p, kind="denoiser") for p in paths]
    ref_doc, ref_parts = loaded[0]
    ref_info = _consistency(ref_doc)
    for p, (doc, parts) in zip(paths[1:], loaded[1:]):
        if doc["config"] != ref_doc["config"]:
            raise ValueError(f"{p}: its architecture, diffusion, text features or VAE differ from {paths[0]}'s, "
                             "so their weights do not correspond")
        if _consistency(doc) != ref_info:
            raise ValueError(f"{p}: not distilled from the same teacher with the same guidance as {paths[0]} "
                             "(meta.consistency differs), or only one of the two is a consistency student")
        _check_same_tensors(p, parts, paths[0], ref_parts)
    averaged = {name: {k: _mean([parts[name][k] for _, parts in loaded], weights, f"{name}/{k}", paths)
                       for k in tensors} for name, tensors in ref_parts.items()}
    meta = {"average": [{"path": str(p), "weight": float(w), "step": doc["meta"].get("step"),
                         "sha256": {n: e["sha256"] for n, e in doc["files"].items()}}
                        for p, w, (doc, _) in zip(paths, weights, loaded)]}
    if ref_info is not None:
        meta["consistency"] = ref_info
    trained = [doc["meta"].get("train_config") for doc, _ in loaded]
    identities = [training_identity(t) for t in trained] if all(isinstance(t, dict) for t in trained) else []
    if identities and all(i == identities[0] for i in identities[1:]):
        # one recipe (runs of it with other seeds or lengths): what a reader of the recipe needs, e.g. a
        # distillation taking the teacher's posterior noise, holds for the average too; mixed recipes record none
        meta["train_config"] = trained[0]
    if "latent_scale" in ref_doc["meta"]:
        meta["latent_scale"] = ref_doc["meta"]["latent_scale"]
    return save_checkpoint(out, "denoiser", ref_doc["config"], averaged, meta)


def _consistency(doc: dict) -> dict | None:
    info = doc["meta"].get("consistency")
    return None if info is None else {k: info.get(k) for k in _SHARED_CONSISTENCY}


def _check_same_tensors(path, parts: dict, ref_path, ref_parts: dict) -> None:
    if parts.keys() != ref_parts.keys():
        raise ValueError(f"{path}: holds other parts ({sorted(parts)}) than {ref_path} ({sorted(ref_parts)})")
    for name, tensors in ref_parts.items():
        other = parts[name]
        if other.keys() != tensors.keys():
            raise ValueError(f"{path}: part {name!r} holds other weights than {ref_path}'s")
        bad = [k for k in tensors if other[k].shape != tensors[k].shape or other[k].dtype != tensors[k].dtype]
        if bad:
            raise ValueError(f"{path}: {name}/{bad[0]} has another shape or dtype than in {ref_path}")


def _mean(tensors: list[torch.Tensor], weights: Sequence[float], name: str, paths) -> torch.Tensor:
    if not tensors[0].is_floating_point():
        # counters and indices cannot be averaged; they must agree
        if any(not torch.equal(t, tensors[0]) for t in tensors[1:]):
            raise ValueError(f"{name}: this integer tensor differs between the checkpoints ({', '.join(map(str, paths))})")
        return tensors[0]
    total = sum(w * t.double() for w, t in zip(weights, tensors))
    return total.to(tensors[0].dtype)
