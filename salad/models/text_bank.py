"""Token features of a fixed caption set, encoded once (the text encoder is frozen during training)."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Sequence

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from ..files import atomic_path

# Entries kept per cache directory: each is ~0.4 GB for the Bandai captions, and a changed caption set or
# encoder leaves its old entry behind. The least recently used go first.
TEXT_CACHE_ENTRIES = 3


class TextBank:
    """Every caption's token features stored flat, gathered into padded batches by index or by caption."""

    def __init__(self, encoder, captions: Sequence[str], chunk: int = 256, progress: bool = True,
                 dtype: torch.dtype = torch.float32):
        captions = self.distinct(captions)
        rows, lengths = [], []
        pooled = torch.zeros(len(captions), encoder.dim)
        for s in tqdm(range(0, len(captions), chunk), desc="text features", disable=not progress):
            out = encoder.encode(captions[s:s + chunk])
            n = out.mask.sum(1)
            for b in range(len(n)):
                rows.append(out.tokens[b, :int(n[b])].to(dtype))
                lengths.append(int(n[b]))
            pooled[s:s + len(n)] = out.pooled.float()
        self._hold(captions, torch.cat(rows), torch.tensor(lengths), pooled)

    @staticmethod
    def distinct(captions: Sequence[str]) -> list[str]:
        """The bank's caption order: "" first (the unconditional row of classifier-free guidance),
        then each caption once, in order of first appearance."""
        return list(dict.fromkeys([""] + list(captions)))

    def _hold(self, captions: list[str], flat: torch.Tensor, lengths: torch.Tensor, pooled: torch.Tensor) -> None:
        self.captions, self.flat, self.lengths, self.pooled = captions, flat, lengths.long(), pooled.float()
        self.index = {c: i for i, c in enumerate(captions)}
        self.offsets = torch.cumsum(torch.cat((torch.zeros(1, dtype=torch.long), self.lengths[:-1])), 0)

    @classmethod
    def from_tensors(cls, captions: Sequence[str], flat: torch.Tensor, lengths: torch.Tensor,
                     pooled: torch.Tensor) -> "TextBank":
        """A bank stored with tensors() (a latent bundle's), without the encoder."""
        if len(captions) != len(lengths) or len(pooled) != len(lengths) or int(lengths.sum()) != len(flat):
            raise ValueError(f"text bank of {len(captions)} captions: {len(lengths)} lengths, {len(pooled)} pooled "
                             f"rows and {len(flat)} token rows (expected {int(lengths.sum())}) do not match")
        bank = cls.__new__(cls)
        bank._hold(list(captions), flat, lengths, pooled)
        return bank

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(token rows, caption lengths, pooled features): what from_tensors takes with the captions."""
        return self.flat, self.lengths, self.pooled

    def gather(self, indices: Sequence[int], multiple: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, L, dim) float32 tokens, zero past each caption's end, and the (B, L) validity mask;
        L is the longest caption's length rounded up to a `multiple`."""
        idx = torch.as_tensor(indices, dtype=torch.long)
        n = self.lengths[idx]
        pos = torch.arange(-(-int(n.max()) // multiple) * multiple)
        mask = pos[None, :] < n[:, None]
        rows = (self.offsets[idx][:, None] + pos[None, :]).clamp(max=len(self.flat) - 1)
        return self.flat[rows].float() * mask[..., None], mask

    def batch(self, captions: Sequence[str], multiple: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Tokens, mask and pooled sentence features of the given (known) captions (gather's `multiple`)."""
        ids = [self.index[c] for c in captions]
        tokens, mask = self.gather(ids, multiple)
        return tokens, mask, self.pooled[ids]


def cached_text_bank(encoder, captions: Sequence[str], cache_dir: str | Path, progress: bool = True,
                     dtype: torch.dtype = torch.float32) -> TextBank:
    """TextBank(encoder, captions) kept in cache_dir, keyed by the encoder (and its weights file) and
    the captions, so a run's restarts and later runs on the same data skip the encoding (about a
    minute for the Bandai captions on two threads). A cache that cannot be read is rebuilt, one that
    cannot be written is skipped; past TEXT_CACHE_ENTRIES entries the least recently used are deleted."""
    distinct = TextBank.distinct(captions)
    spec = encoder.spec()
    weights = spec.get("weights")
    stat = os.stat(weights) if weights and os.path.isfile(weights) else None
    key = hashlib.sha256(json.dumps({"spec": spec, "dtype": str(dtype), "captions": distinct,
                                     "weights": stat and [stat.st_size, stat.st_mtime_ns]},
                                    sort_keys=True).encode()).hexdigest()[:32]
    path = Path(cache_dir) / f"text-features-{key}.safetensors"
    if path.is_file():
        try:
            t = load_file(str(path))
            bank = TextBank.from_tensors(distinct, t["flat"], t["lengths"], t["pooled"])
        except (OSError, SafetensorError, KeyError, ValueError):
            pass
        else:
            try:
                os.utime(path)            # used now: the last to be pruned
            except OSError:
                pass
            return bank
    bank = TextBank(encoder, distinct, progress=progress, dtype=dtype)
    flat, lengths, pooled = bank.tensors()
    try:
        with atomic_path(path) as tmp:
            save_file({"flat": flat.contiguous(), "lengths": lengths, "pooled": pooled.contiguous()}, str(tmp))
        _prune(path.parent)
    except OSError:
        pass
    return bank


def _prune(cache_dir: Path) -> None:
    entries = sorted(cache_dir.glob("text-features-*.safetensors"), key=lambda p: p.stat().st_mtime_ns, reverse=True)
    for old in entries[TEXT_CACHE_ENTRIES:]:
        old.unlink(missing_ok=True)
