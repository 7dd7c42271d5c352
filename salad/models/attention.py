"""Multi-head attention whose probability maps a controller can observe and replace.

With no controller attached the module calls PyTorch's fused
scaled_dot_product_attention and never materialises the maps (except over a few keys,
where the plain product is faster). With one attached it computes softmax(QK^T)
explicitly and hands the maps to the controller, which returns the maps to use (the
same tensor, or an edited one) — the hook that zero-shot editing and attention
capture are built on.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
import torch.nn as nn
import torch.nn.functional as F

from .dropout import dropout
from .stacked import StackedLinears

TEMPORAL, SKELETAL, CROSS = "temporal", "skeletal", "cross"
# Over this many keys or fewer the explicit softmax(QK^T)V beats the fused kernel: on a 2-core CPU the
# skeletal attention's 7 keys took 2.5-3x as long fused (0.63 against 0.26 ms per layer for one 9.8 s
# motion, 1.8 against 0.75 ms for four), while over the temporal attention's 49 frames the two are close.
FUSED_MIN_KEYS = 16


@dataclass
class AttentionCall:
    """What a controller is told about one attention call.

    probs has shape (N, heads, Lq, Lk) where, for a batch of B motions with T latent
    frames and J body parts:
      temporal: N = B*J, Lq = Lk = T   (rows ordered b-major: n = b*J + j)
      skeletal: N = B*T, Lq = Lk = J   (n = b*T + t)
      cross:    N = B,   Lq = T*J, Lk = text tokens  (query q = t*J + j)
    """

    kind: str
    layer: int
    probs: torch.Tensor
    batch: int
    frames: int
    parts: int


class AttentionController(Protocol):
    """Returns the maps to use. It may also have wants(kind, layer) -> bool, asked before each call:
    False runs that call fused, without maps and without calling the controller."""

    def __call__(self, call: AttentionCall) -> torch.Tensor: ...


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int, kind: str, context_dim: int | None = None, dropout: float = 0.0):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} is not divisible by heads {heads}")
        self.kind, self.heads, self.dropout = kind, heads, dropout
        self.layer = -1  # set by the denoiser so controllers know where a map comes from
        context_dim = context_dim or dim
        self.to_q = nn.Linear(dim, dim)
        self.to_k = nn.Linear(context_dim, dim)
        self.to_v = nn.Linear(context_dim, dim)
        self.to_out = nn.Linear(dim, dim)
        self.controller: AttentionController | None = None
        self._qkv = StackedLinears()

    def _heads(self, x: torch.Tensor) -> torch.Tensor:
        N, L, D = x.shape
        return x.view(N, L, self.heads, D // self.heads).transpose(1, 2)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None,
                key_mask: torch.Tensor | None = None, shape: tuple[int, int, int] = (0, 0, 0)) -> torch.Tensor:
        """x (N, Lq, D); context (N, Lk, Dc) or None for self-attention; key_mask (N, Lk)
        bool, True = may be attended. shape = (batch, frames, parts) for controllers."""
        if context is None:
            q, k, v = map(self._heads, self._qkv(x, [self.to_q, self.to_k, self.to_v]).chunk(3, dim=-1))
        else:
            q, k, v = self._heads(self.to_q(x)), self._heads(self.to_k(context)), self._heads(self.to_v(context))
        mask = None if key_mask is None else key_mask[:, None, None, :]
        p_drop = self.dropout if self.training else 0.0
        controller = self.controller
        if controller is not None and hasattr(controller, "wants") and not controller.wants(self.kind, self.layer):
            controller = None
        if controller is None and p_drop == 0.0 and k.shape[-2] > FUSED_MIN_KEYS:
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        else:   # explicit maps: a controller observes them, training drops some (cheaply, see dropout.py), or few keys
            scores = (q @ k.transpose(-2, -1)) * (q.shape[-1] ** -0.5)
            if mask is not None:
                scores = scores.masked_fill(~mask, float("-inf"))
            probs = scores.softmax(dim=-1)
            if mask is not None:    # a row with every key masked attends to nothing, as in the fused kernel
                probs = probs.masked_fill(~mask.any(-1, keepdim=True), 0.0)
            if controller is not None:
                probs = controller(AttentionCall(self.kind, self.layer, probs, *shape))
            probs = dropout(probs, p_drop)
            out = probs.to(v.dtype) @ v
        N, H, L, Dh = out.shape
        return self.to_out(out.transpose(1, 2).reshape(N, L, H * Dh))
