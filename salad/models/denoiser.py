"""Skeleton-aware denoiser (SALAD §3.2, supp. A.2).

Tokens are (latent frame, body part) pairs. Each layer runs temporal attention (each
part over time), skeletal attention (the 7 parts within a frame), cross-attention to
the text tokens and a feed-forward net; every sub-block is pre-LayerNorm, modulated by
FiLM from the diffusion timestep, and residual. Layers are joined U-Net style: the
outputs of the first half feed the second half through skip connections.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import torch
import torch.nn as nn
import torch.nn.functional as F

from .attention import CROSS, SKELETAL, TEMPORAL, Attention
from .dropout import Dropout
from .stacked import StackedLinears

# Guidance scales of a few units are spread over the sinusoid's frequencies like timesteps.
GUIDANCE_EMBED_SCALE = 100.0


@dataclass
class DenoiserConfig:
    latent_dim: int = 32
    parts: int = 7
    dim: int = 256
    heads: int = 8
    ff_dim: int = 1024
    layers: int = 5
    dropout: float = 0.1
    text_dim: int = 512
    # False gives the "w/o CrossAttn" ablation of SALAD Table 3: the sentence feature is
    # concatenated to every motion token and the layers use self-attention only.
    cross_attention: bool = True
    # Lets one model generate both fixed-length motions (key-padding mask) and
    # "auto"-length ones on a full canvas whose end the VAE's activation channel marks.
    length_modes: bool = True
    # A consistency-distilled student takes the classifier-free guidance scale as a condition
    # (embedded like the timestep), so one forward per step stands in for CFG's two.
    guidance_embedding: bool = False
    # Width of the frame and timestep sinusoids (0: dim). A model widened from a narrower one
    # (widen.py) keeps its parent's sinusoids, tiled over the width, so it starts as that model.
    sinusoid_dim: int = 0

    @property
    def sinusoid_width(self) -> int:
        return self.sinusoid_dim or self.dim


def sinusoid(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """Transformer sinusoidal embedding of (any shape) positions -> (..., dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=positions.device) / half)
    args = positions.float()[..., None] * freqs
    return torch.cat((torch.sin(args), torch.cos(args)), dim=-1)


class FiLM(nn.Module):
    """Holds one sub-block's projection of the timestep embedding to (scale, shift); the block's
    output becomes out * (1 + scale) + shift (`modulate`). The denoiser applies every FiLM's
    projection in one product (Denoiser.modulations), so this module has no forward."""

    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Sequential(nn.SiLU(), nn.Linear(dim, 2 * dim))


def modulate(h: torch.Tensor, scale1: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """h (B, ..., D) * scale1 + shift, with scale1 = 1 + scale and shift (B, D) from one FiLM."""
    extra = (1,) * (h.ndim - 2)
    return torch.addcmul(shift.view(shift.shape[0], *extra, -1), h, scale1.view(scale1.shape[0], *extra, -1))


class STLayer(nn.Module):
    def __init__(self, c: DenoiserConfig, index: int):
        super().__init__()
        d = c.dim
        self.norm_t, self.norm_s, self.norm_f = nn.LayerNorm(d), nn.LayerNorm(d), nn.LayerNorm(d)
        self.temporal = Attention(d, c.heads, TEMPORAL, dropout=c.dropout)
        self.skeletal = Attention(d, c.heads, SKELETAL, dropout=c.dropout)
        self.film_t, self.film_s, self.film_f = FiLM(d), FiLM(d), FiLM(d)
        self.cross = None
        if c.cross_attention:
            self.norm_c, self.norm_text = nn.LayerNorm(d), nn.LayerNorm(d)
            self.cross = Attention(d, c.heads, CROSS, dropout=c.dropout)
            self.film_c = FiLM(d)
        self.ff = nn.Sequential(nn.Linear(d, c.ff_dim), nn.GELU(), Dropout(c.dropout), nn.Linear(c.ff_dim, d))
        self.drop = Dropout(c.dropout)
        for attn in self.attentions():
            attn.layer = index

    def attentions(self) -> list[Attention]:
        return [a for a in (self.temporal, self.skeletal, self.cross) if a is not None]

    def films(self) -> list[FiLM]:
        """In the order forward applies them."""
        return [f for f in (self.film_t, self.film_s, self.film_c if self.cross is not None else None, self.film_f)
                if f is not None]

    def forward(self, x, scale1, shift, text, text_mask, frame_mask):
        """scale1, shift (B, len(films()), D): this layer's FiLM modulations."""
        B, T, J, D = x.shape
        shape = (B, T, J)
        films = iter(zip(scale1.unbind(1), shift.unbind(1)))
        # contiguous: a strided (B*J, T, D) view would send the q/k/v projections down a slower batched product
        h = self.norm_t(x).transpose(1, 2).reshape(B * J, T, D).contiguous()
        key_mask = None if frame_mask is None else frame_mask.repeat_interleave(J, dim=0)
        h = self.temporal(h, key_mask=key_mask, shape=shape).reshape(B, J, T, D).transpose(1, 2)
        x = x + self.drop(modulate(h, *next(films)))

        h = self.skeletal(self.norm_s(x).reshape(B * T, J, D), shape=shape).reshape(B, T, J, D)
        x = x + self.drop(modulate(h, *next(films)))

        if self.cross is not None:
            h = self.cross(self.norm_c(x).reshape(B, T * J, D), self.norm_text(text), key_mask=text_mask, shape=shape)
            x = x + self.drop(modulate(h.reshape(B, T, J, D), *next(films)))

        return x + self.drop(modulate(self.ff(self.norm_f(x)), *next(films)))


class Denoiser(nn.Module):
    def __init__(self, config: DenoiserConfig | None = None):
        super().__init__()
        self.config = c = config or DenoiserConfig()
        d, s = c.dim, c.sinusoid_width
        if s <= 0 or s % 2 or d % s:
            raise ValueError(f"sinusoid_dim {s} must be positive, even and divide dim {d}")
        in_dim = c.latent_dim + (d if not c.cross_attention else 0)
        self.input = nn.Sequential(nn.Linear(in_dim, d), nn.ReLU(), nn.Linear(d, d))
        self.part_embedding = nn.Parameter(torch.zeros(c.parts, d))
        nn.init.normal_(self.part_embedding, std=0.02)
        self.pe_drop = Dropout(c.dropout)
        self.time_mlp = nn.Sequential(nn.Linear(s, d), nn.SiLU(), nn.Linear(d, d))
        self.length_mode = nn.Embedding(2, d) if c.length_modes else None
        self.guidance_mlp = None
        if c.guidance_embedding:
            self.guidance_mlp = nn.Sequential(nn.Linear(s, d), nn.SiLU(), nn.Linear(d, d))
            # zero at first, so a student initialised from its teacher starts as the teacher
            nn.init.zeros_(self.guidance_mlp[-1].weight)
            nn.init.zeros_(self.guidance_mlp[-1].bias)
        self.text_proj = nn.Linear(c.text_dim, d)

        n_skip = c.layers // 2
        self.layers = nn.ModuleList(STLayer(c, i) for i in range(c.layers))
        self.skip_proj = nn.ModuleList(nn.Linear(2 * d, d) for _ in range(n_skip))
        self.n_skip = n_skip
        self.output = nn.Sequential(nn.LayerNorm(d), nn.Linear(d, d), nn.ReLU(), nn.Linear(d, c.latent_dim))
        self._films = StackedLinears()

    def attentions(self) -> list[Attention]:
        return [a for layer in self.layers for a in layer.attentions()]

    def modulations(self, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every FiLM's (1 + scale, shift), each (B, films, D), from one product: at batch 1 the
        twenty-odd (1, d) projections, one per sub-block, cost more in calls than in arithmetic."""
        projections = [f.proj[1] for layer in self.layers for f in layer.films()]
        scale, shift = self._films(F.silu(emb), projections).unflatten(-1, (-1, 2, self.config.dim)).unbind(2)
        return 1 + scale, shift

    def set_controller(self, controller) -> None:
        """Attach a controller to every attention module (None detaches)."""
        for a in self.attentions():
            a.controller = controller

    @contextmanager
    def controlled(self, controller) -> Iterator[Denoiser]:
        """The block runs with `controller` on every attention module (None: plain attention);
        it is detached however the block ends, so a failed sampling leaves no edit behind."""
        self.set_controller(controller)
        try:
            yield self
        finally:
            self.set_controller(None)

    def forward(self, z: torch.Tensor, t: torch.Tensor, text: torch.Tensor, text_mask: torch.Tensor | None = None,
                frame_mask: torch.Tensor | None = None, pooled_text: torch.Tensor | None = None,
                auto_length: torch.Tensor | None = None, guidance: torch.Tensor | None = None) -> torch.Tensor:
        """z (B, T, 7, latent_dim) noisy latents; t (B,) timesteps; text (B, L, text_dim) token
        features with text_mask (B, L) True for real tokens; frame_mask (B, T) True for real
        latent frames; pooled_text (B, text_dim) for the no-cross-attention variant;
        auto_length (B,) bool, True for full-canvas (length decided by the decoder) samples;
        guidance (B,) the CFG scale a distilled student is to reproduce (guidance_embedding only)."""
        B, T, J, _ = z.shape
        c = self.config
        # masks that mask nothing (one prompt, a fixed length) only cost; asking is a sync on a GPU, so only here
        if z.device.type == "cpu" and not torch.compiler.is_compiling():
            text_mask = None if text_mask is not None and bool(text_mask.all()) else text_mask
            frame_mask = None if frame_mask is not None and bool(frame_mask.all()) else frame_mask
        if c.cross_attention:
            h = self.input(z)
            text_tokens = self.text_proj(text)
        else:
            if pooled_text is None:
                raise ValueError("this denoiser has no cross-attention and needs pooled_text")
            sent = self.text_proj(pooled_text)[:, None, None, :].expand(B, T, J, c.dim)
            h = self.input(torch.cat((z, sent), dim=-1))
            text_tokens = None
        s = c.sinusoid_width
        frames = sinusoid(torch.arange(T, device=z.device), s).repeat(1, c.dim // s)
        h = h + frames.to(h.dtype)[None, :, None, :] + self.part_embedding
        h = self.pe_drop(h)

        emb = self.time_mlp(sinusoid(t, s).to(h.dtype))
        if self.length_mode is not None:
            mode = torch.zeros(B, dtype=torch.long, device=z.device) if auto_length is None else auto_length.long()
            emb = emb + self.length_mode(mode)
        if self.guidance_mlp is not None:
            if guidance is None:
                raise ValueError("this denoiser is a distilled student and needs the guidance scale")
            emb = emb + self.guidance_mlp(sinusoid(guidance * GUIDANCE_EMBED_SCALE, s).to(h.dtype))

        # every layer has the same sub-blocks, so the modulations split evenly: (B, layers, films per layer, D)
        scale1, shift = (m.unflatten(1, (len(self.layers), -1)) for m in self.modulations(emb))
        skips = []
        for i, layer in enumerate(self.layers):
            if i >= len(self.layers) - self.n_skip:
                h = self.skip_proj[i - (len(self.layers) - self.n_skip)](torch.cat((h, skips.pop()), dim=-1))
            h = layer(h, scale1[:, i], shift[:, i], text_tokens, text_mask, frame_mask)
            if i < self.n_skip:
                skips.append(h)
        return self.output(h)
