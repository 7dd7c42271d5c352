"""Networks shared by the text-motion evaluator and the motion classifiers.

The motion side follows Guo et al. (CVPR 2022): a movement encoder of two stride-2
1-D convolutions over the 259 non-contact feature channels, then a bidirectional GRU
whose final states give the embedding. Widths are configurable so it trains on a
small CPU. The text side replaces Guo's GloVe + part-of-speech inputs (GloVe is not
available here) with the frozen per-token MiniLM features, read by a trainable BiGRU.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.nn.utils.rnn import pack_padded_sequence

from ..checkpoint import CheckpointError, load_checkpoint, load_state_strict, save_checkpoint
from ..config import ConfigError, from_dict, to_dict

CONTACT_CHANNELS = 4   # the last 4 of the 263: foot contacts, left out as in Guo et al.
DOWNSAMPLE = 4         # two stride-2 convolutions


@dataclass
class MotionEncoderConfig:
    input_dim: int = 259
    conv_channels: int = 256    # Guo et al.: 512
    conv_dropout: float = 0.2
    gru_hidden: int = 256       # per direction; Guo et al.: 1024 for the motion GRU
    output_dim: int = 512


@dataclass
class TextHeadConfig:
    input_dim: int = 384        # MiniLM token features
    gru_hidden: int = 256
    dropout: float = 0.1
    output_dim: int = 512


def downsampled_lengths(lengths: torch.Tensor) -> torch.Tensor:
    """Valid steps after the movement encoder: floor(T / 2) twice."""
    return torch.div(torch.div(lengths, 2, rounding_mode="floor"), 2, rounding_mode="floor")


def _step_mask(lengths: torch.Tensor, steps: int) -> torch.Tensor:
    return torch.arange(steps, device=lengths.device)[None, :] < lengths[:, None]


class MovementEncoder(nn.Module):
    """(B, T, C) -> (B, T/4, channels) snippet features.

    The input and each convolution's output are zeroed past the motion's end, so a
    motion's features do not depend on what or how much padding its batch carries.
    """

    def __init__(self, cfg: MotionEncoderConfig):
        super().__init__()
        c = cfg.conv_channels
        self.conv1 = nn.Conv1d(cfg.input_dim, c, 4, 2, 1)
        self.conv2 = nn.Conv1d(c, c, 4, 2, 1)
        self.drop = nn.Dropout(cfg.conv_dropout)
        self.act = nn.LeakyReLU(0.2)
        self.out = nn.Linear(c, c)

    def forward(self, x: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        half = torch.div(lengths, 2, rounding_mode="floor")
        quarter = downsampled_lengths(lengths)
        x = x * _step_mask(lengths, x.shape[1])[..., None].to(x.dtype)
        h = self.act(self.drop(self.conv1(x.transpose(1, 2))))
        h = h * _step_mask(half, h.shape[-1])[:, None, :].to(h.dtype)
        h = self.act(self.drop(self.conv2(h)))
        h = h * _step_mask(quarter, h.shape[-1])[:, None, :].to(h.dtype)
        return self.out(h.transpose(1, 2)), quarter


class BiGRUEncoder(nn.Module):
    """Variable-length sequence -> fixed vector from the final states of a bidirectional GRU."""

    def __init__(self, input_dim: int, hidden: int, output_dim: int, dropout: float = 0.0):
        super().__init__()
        self.inp = nn.Linear(input_dim, hidden)
        self.gru = nn.GRU(hidden, hidden, batch_first=True, bidirectional=True)
        self.h0 = nn.Parameter(torch.zeros(2, 1, hidden))
        self.head = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.LayerNorm(hidden), nn.LeakyReLU(0.2),
                                  nn.Dropout(dropout), nn.Linear(hidden, output_dim))

    def forward(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        if (lengths < 1).any():
            raise ValueError("every sequence needs at least one step")
        h = self.inp(x)
        packed = pack_padded_sequence(h, lengths.cpu(), batch_first=True, enforce_sorted=False)
        _, last = self.gru(packed, self.h0.expand(-1, x.shape[0], -1).contiguous())
        return self.head(torch.cat((last[0], last[1]), dim=-1))


class MotionEncoder(nn.Module):
    """Normalised features (B, T, 259) with lengths (B,) -> (B, output_dim)."""

    def __init__(self, cfg: MotionEncoderConfig, chunk: int = 32):
        super().__init__()
        self.cfg = cfg
        self.chunk = chunk
        self.movement = MovementEncoder(cfg)
        self.sequence = BiGRUEncoder(cfg.conv_channels, cfg.gru_hidden, cfg.output_dim)

    def forward(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.cfg.input_dim:
            raise ValueError(f"motion encoder expects {self.cfg.input_dim} channels, got {x.shape[-1]}")
        if (lengths < DOWNSAMPLE).any():
            raise ValueError(f"motions must have at least {DOWNSAMPLE} frames, got {int(lengths.min())}")
        # Convolving each run of similar lengths with its own padding halves the cost on batches of mixed
        # lengths; the masking in MovementEncoder makes the result independent of the split.
        order = torch.argsort(lengths, stable=True)
        steps = downsampled_lengths(lengths)
        width = int(steps.max())
        parts = []
        for s in range(0, len(order), self.chunk):
            idx = order[s:s + self.chunk]
            part, _ = self.movement(x[idx, :int(lengths[idx].max())], lengths[idx])
            parts.append(F.pad(part, (0, 0, 0, width - part.shape[1])))
        h = torch.cat(parts)[torch.argsort(order)]
        return self.sequence(h, steps)


class TextEncoderHead(nn.Module):
    """Frozen per-token text features (B, L, 384) with mask (B, L) -> (B, output_dim)."""

    def __init__(self, cfg: TextHeadConfig):
        super().__init__()
        self.cfg = cfg
        self.sequence = BiGRUEncoder(cfg.input_dim, cfg.gru_hidden, cfg.output_dim, cfg.dropout)

    def forward(self, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        # the padded tail is never read: the packed GRU stops at each prompt's last real token
        return self.sequence(tokens, mask.sum(1))


def save_scorer(path: str | Path, kind: str, model: nn.Module, mean: np.ndarray, std: np.ndarray,
                meta: dict[str, Any] | None = None) -> Path:
    """An evaluation network (its `cfg` as the config) with the feature statistics it normalises by."""
    stats = {"mean": torch.as_tensor(np.asarray(mean, np.float32)), "std": torch.as_tensor(np.asarray(std, np.float32))}
    return save_checkpoint(path, kind, to_dict(model.cfg), {"model": model.state_dict(), "stats": stats}, meta or {})


def load_scorer(path: str | Path, kind: str, config_cls: type, build: Callable[[Any], nn.Module]):
    """-> (network in eval mode, mean, std, config.json document) of a checkpoint written by save_scorer."""
    doc, parts = load_checkpoint(path, kind)
    try:
        cfg = from_dict(config_cls, doc["config"], f"{path}/config.json")
    except ConfigError as e:
        raise CheckpointError(str(e)) from None
    for part in ("model", "stats"):
        if part not in parts:
            raise CheckpointError(f"{path}: {kind} checkpoint lacks its {part!r} part")
    stats = parts["stats"]
    if set(stats) != {"mean", "std"}:
        raise CheckpointError(f"{path}: stats part must hold 'mean' and 'std', has {sorted(stats)}")
    model = build(cfg)
    load_state_strict(model, parts["model"], str(path))
    return model.eval(), stats["mean"].numpy(), stats["std"].numpy(), doc
