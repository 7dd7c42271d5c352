"""Doubling a trained denoiser's width without changing what it computes (Net2WiderNet).

Every channel of the residual stream, every attention head and every feed-forward unit is
duplicated. LayerNorm sees each value twice, so its mean and variance, and its output up to
the duplication, stay the same; a layer reading duplicated channels gets each weight halved on
both copies, so it sums to the old product. The wide model therefore starts exactly where the
narrow one plateaued, and its extra capacity trains from there (dropout gives the two copies
different gradients, which splits them). The positional and timestep sinusoids are kept at the
parent's width and tiled (DenoiserConfig.sinusoid_dim), since a wider sinusoid is a different
function of the frame and the timestep.
"""
from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn as nn

from .denoiser import Denoiser, DenoiserConfig


def widened_config(c: DenoiserConfig) -> DenoiserConfig:
    """The config widen() produces: twice the width, heads and feed-forward units."""
    return replace(c, dim=2 * c.dim, heads=2 * c.heads, ff_dim=2 * c.ff_dim, sinusoid_dim=c.sinusoid_width)


def widen(narrow: Denoiser) -> Denoiser:
    c = narrow.config
    if not c.cross_attention:
        raise ValueError("widening applies to the cross-attention denoiser")
    wide = Denoiser(widened_config(c))
    d, ff, s = c.dim, c.ff_dim, c.sinusoid_width
    dup, same = _twice(d), torch.arange(s)
    blocks = torch.cat((dup, d + dup))          # two d-wide halves, each duplicated: FiLM's (scale, shift), skips
    maps = {"input.0": (dup, torch.arange(c.latent_dim)), "input.2": (dup, dup),
            "time_mlp.0": (dup, same), "time_mlp.2": (dup, dup),
            "guidance_mlp.0": (dup, same), "guidance_mlp.2": (dup, dup),
            "text_proj": (dup, torch.arange(c.text_dim)),
            "output.1": (dup, dup), "output.3": (torch.arange(c.latent_dim), dup)}
    maps.update({f"skip_proj.{i}": (dup, blocks) for i in range(narrow.n_skip)})
    for i in range(c.layers):
        p = f"layers.{i}."
        for a in ("temporal", "skeletal", "cross"):
            maps.update({f"{p}{a}.{w}": (dup, dup) for w in ("to_q", "to_k", "to_v", "to_out")})
        maps.update({f"{p}film_{f}.proj.1": (blocks, dup) for f in "tscf"})
        maps.update({f"{p}ff.0": (_twice(ff), dup), f"{p}ff.3": (dup, _twice(ff))})
    old = dict(narrow.named_modules())
    with torch.no_grad():
        for name, module in wide.named_modules():
            if isinstance(module, nn.Linear):
                rows, cols = maps[name]
                _copy_linear(module, old[name], rows, cols)
            elif isinstance(module, nn.LayerNorm):
                module.weight.copy_(old[name].weight[dup])
                module.bias.copy_(old[name].bias[dup])
            elif isinstance(module, nn.Embedding):
                module.weight.copy_(old[name].weight[:, dup])
        wide.part_embedding.copy_(narrow.part_embedding[:, dup])
    return wide.train(narrow.training)


def _twice(n: int) -> torch.Tensor:
    """Index of the old channel behind each new one: the old channels, then their copies."""
    return torch.arange(n).repeat(2)


def _copy_linear(new: nn.Linear, old: nn.Linear, rows: torch.Tensor, cols: torch.Tensor) -> None:
    # a column read twice has its weight split between the two copies
    reads = torch.bincount(cols, minlength=old.in_features).to(old.weight.dtype)
    new.weight.copy_(old.weight[rows][:, cols] / reads[cols])
    new.bias.copy_(old.bias[rows])
