"""Checkpoints are directories: config.json plus one safetensors file per part.

Nothing is ever unpickled. Every file's SHA-256 is recorded in config.json and checked
on load, so a truncated or altered file gives a clear error instead of garbage
weights. Saving writes a sibling temporary directory and renames it into place, so a
crash mid-save never leaves a half-written checkpoint where a good one was.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from .files import ordinary_permissions

FORMAT = "salad-checkpoint"
VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that is missing, corrupt, or not what the caller asked for."""


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def recover_checkpoint(path: str | Path) -> bool:
    """Put back the previous copy if a save died between its two renames; -> whether `path` exists.

    A save moves the old checkpoint aside before renaming the new one in, so a kill at that moment
    leaves only `.NAME.old-PID`, which is still a whole checkpoint."""
    path = Path(path)
    if not path.exists():
        olds = sorted(path.parent.glob(f".{path.name}.old-*"), key=lambda d: d.stat().st_mtime)
        olds = [d for d in olds if (d / "config.json").is_file()]
        if olds:
            os.replace(olds[-1], path)
            _fsync_dir(path.parent)
    return path.exists()


def save_checkpoint(path: str | Path, kind: str, config: dict[str, Any],
                    parts: dict[str, dict[str, torch.Tensor]], meta: dict[str, Any] | None = None) -> Path:
    """Write `parts` (name -> flat tensor dict) and a JSON description to directory `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    recover_checkpoint(path)
    # leftovers of a writer killed mid-save: unfinished copies, and old copies once a new one is in place
    stale = [*path.parent.glob(f".{path.name}.tmp-*")]
    if path.exists():
        stale += path.parent.glob(f".{path.name}.old-*")
    for d in stale:
        shutil.rmtree(d, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.tmp-"))
    try:
        files = {}
        for name, tensors in parts.items():
            if not name.replace("_", "").replace("-", "").isalnum():
                raise ValueError(f"bad checkpoint part name {name!r}")
            f = tmp / f"{name}.safetensors"
            save_file({k: v.detach().contiguous().cpu() for k, v in tensors.items()}, str(f))
            files[name] = {"file": f.name, "sha256": _sha256(f)}
        doc = {"format": FORMAT, "version": VERSION, "kind": kind, "config": config,
               "files": files, "meta": meta or {}}
        (tmp / "config.json").write_text(json.dumps(doc, indent=2, sort_keys=True))
        for f in tmp.iterdir():
            ordinary_permissions(f)
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        ordinary_permissions(tmp)
        old = None
        if path.exists():
            old = path.parent / f".{path.name}.old-{os.getpid()}"
            os.replace(path, old)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def read_checkpoint_config(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    path = Path(path)
    recover_checkpoint(path)
    cfg_file = path / "config.json"
    if not path.is_dir():
        raise CheckpointError(f"{path}: not a checkpoint directory")
    if not cfg_file.is_file():
        raise CheckpointError(f"{path}: no config.json, so this is not a salad checkpoint")
    try:
        doc = json.loads(cfg_file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{cfg_file}: corrupt JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"{path}: config.json is not a {FORMAT} file (foreign checkpoint?)")
    if doc.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {doc.get('version')} is not supported (expected {VERSION})")
    if kind is not None and doc.get("kind") != kind:
        raise CheckpointError(f"{path}: holds a {doc.get('kind')!r} checkpoint, expected {kind!r}")
    return doc


def load_checkpoint(path: str | Path, kind: str | None = None, verify: bool = True):
    """-> (config.json document, {part name: tensor dict})."""
    path = Path(path)
    doc = read_checkpoint_config(path, kind)
    parts = {}
    for name, entry in doc.get("files", {}).items():
        f = path / entry["file"]
        if not f.is_file():
            raise CheckpointError(f"{path}: missing {entry['file']}")
        if verify and _sha256(f) != entry["sha256"]:
            raise CheckpointError(f"{f}: contents do not match the recorded checksum (corrupt or modified)")
        try:
            parts[name] = load_file(str(f))
        except (SafetensorError, OSError, ValueError) as e:
            raise CheckpointError(f"{f}: cannot be read as safetensors ({e})") from None
    return doc, parts


def load_state_strict(module: torch.nn.Module, state: dict[str, torch.Tensor], where: str) -> None:
    """load_state_dict with an error that names the checkpoint and the mismatch. A module with an
    upgrade_state(state) method is first given the state to bring it to its current layout."""
    if hasattr(module, "upgrade_state"):
        state = module.upgrade_state(state)
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    wrong = sorted(k for k in set(own) & set(state) if own[k].shape != state[k].shape)
    if missing or unexpected or wrong:
        detail = []
        if missing:
            detail.append(f"missing {missing[:5]}")
        if unexpected:
            detail.append(f"unexpected {unexpected[:5]}")
        if wrong:
            detail.append(f"shape mismatch {[(k, tuple(state[k].shape), tuple(own[k].shape)) for k in wrong[:3]]}")
        raise CheckpointError(f"{where}: weights do not fit the model ({'; '.join(detail)})")
    module.load_state_dict(state)
