"""Dropout with a cheaper random mask, for CPU training.

On this CPU, `F.dropout` spent ~30% of a denoiser training step drawing one Bernoulli sample per
element from the Mersenne-Twister generator. Here one 64-bit draw serves four elements (each gets
16 random bits), which makes dropout ~2.7× faster. The drop probability is p rounded to 1/65536,
and survivors are scaled by the exact inverse of the keep probability, so the expectation is kept.
It uses torch's default generator, so `torch.manual_seed` and saved RNG state reproduce it.
"""
from __future__ import annotations

import torch
import torch.nn as nn

_LEVELS = 1 << 16


def dropout(x: torch.Tensor, p: float, training: bool = True) -> torch.Tensor:
    if not training or p <= 0.0:
        return x
    dropped = round(p * _LEVELS)
    if dropped >= _LEVELS:
        return torch.zeros_like(x)
    n = x.numel()
    bits = torch.empty((n + 3) // 4, dtype=torch.int64, device=x.device).random_(-(1 << 63), None)
    r = bits.view(torch.int16)[:n].view(x.shape)          # uniform over [-32768, 32767]
    keep = r >= (dropped - _LEVELS // 2)
    # one multiply by a pre-scaled mask: masked_fill was 2× slower forward and backward
    return x * (keep.to(x.dtype) * (_LEVELS / (_LEVELS - dropped)))


class Dropout(nn.Module):
    """Drop-in for nn.Dropout (no parameters, so checkpoints are unaffected)."""

    def __init__(self, p: float = 0.5):
        super().__init__()
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"dropout probability must be in [0, 1], got {p}")
        self.p = p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return dropout(x, self.p, self.training)

    def extra_repr(self) -> str:
        return f"p={self.p}"
