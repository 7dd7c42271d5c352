"""Token features of a fixed caption set, encoded once (the text encoder is frozen during training)."""
from __future__ import annotations

from typing import Sequence

import torch
from tqdm import tqdm


class TextBank:
    """Every caption's token features stored flat, gathered into padded batches by index or by caption."""

    def __init__(self, encoder, captions: Sequence[str], chunk: int = 256, progress: bool = True,
                 dtype: torch.dtype = torch.float32):
        # "" is always present: it is the unconditional row of classifier-free guidance
        self.captions = list(dict.fromkeys([""] + list(captions)))
        self.index = {c: i for i, c in enumerate(self.captions)}
        rows, lengths = [], []
        self.pooled = torch.zeros(len(self.captions), encoder.dim)
        for s in tqdm(range(0, len(self.captions), chunk), desc="text features", disable=not progress):
            out = encoder.encode(self.captions[s:s + chunk])
            n = out.mask.sum(1)
            for b in range(len(n)):
                rows.append(out.tokens[b, :int(n[b])].to(dtype))
                lengths.append(int(n[b]))
            self.pooled[s:s + len(n)] = out.pooled.float()
        self.lengths = torch.tensor(lengths)
        self.offsets = torch.cumsum(torch.cat((torch.zeros(1, dtype=torch.long), self.lengths[:-1])), 0)
        self.flat = torch.cat(rows)

    def gather(self, indices: Sequence[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, L, dim) float32 tokens, zero past each caption's end, and the (B, L) validity mask."""
        idx = torch.as_tensor(indices, dtype=torch.long)
        n = self.lengths[idx]
        pos = torch.arange(int(n.max()))
        mask = pos[None, :] < n[:, None]
        rows = (self.offsets[idx][:, None] + pos[None, :]).clamp(max=len(self.flat) - 1)
        return self.flat[rows].float() * mask[..., None], mask

    def batch(self, captions: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Tokens, mask and pooled sentence features of the given (known) captions."""
        ids = [self.index[c] for c in captions]
        tokens, mask = self.gather(ids)
        return tokens, mask, self.pooled[ids]
