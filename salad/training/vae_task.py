"""Training task for the skeleto-temporal VAE."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from ..config import to_dict, validate
from ..data.dataset import MotionDataset, WindowSampler
from ..models.vae import MotionVAE
from ..checkpoint import load_state_strict
from ..models.io import load_vae, save_vae
from .balance import window_weights
from .configs import VAETrainConfig


class VAETraining(nn.Module):
    """forward(batch) -> (loss, logs); wrapping the loss in forward lets DDP sync gradients."""

    def __init__(self, vae: MotionVAE):
        super().__init__()
        self.vae = vae

    def forward(self, batch: dict):
        act = batch["activation"]
        total, logs, _, _ = self.vae.loss(batch["features"], act, valid=act > 0.5, eps=batch["eps"])
        logs["loss"] = logs.pop("total")
        return total, logs


class VAETask:
    kind = "vae"

    def __init__(self, cfg: VAETrainConfig, dataset: MotionDataset | None = None):
        self.cfg = cfg
        validate(cfg)
        self.dataset = dataset or MotionDataset(cfg.data.root, "train", min_frames=cfg.data.min_frames,
                                                max_frames=10 ** 9, require_captions=False)
        self.sampler = WindowSampler(self.dataset, cfg.data.window, cfg.window_overhang,
                                     window_weights(self.dataset, cfg.data.balance))
        torch.manual_seed(cfg.run.seed)
        self.model = VAETraining(MotionVAE(cfg.model))

    def batch(self, rng: np.random.Generator) -> dict:
        b = self.sampler.batch(self.cfg.optim.batch_size, rng)
        B, T = b["activation"].shape
        # The reparameterisation noise belongs to the batch, so a step is a pure function
        # of it (exact resume, and DDP shards that add up to the single-process step).
        g = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        b["eps"] = torch.randn(B, T // 4, 7, self.cfg.model.latent_dim, generator=g)
        return b

    def loss(self, model: nn.Module, batch: dict):
        return model(batch)

    def config_dict(self) -> dict:
        return to_dict(self.cfg)

    @torch.no_grad()
    def latent_scale(self, vae: MotionVAE, n: int = 512) -> float:
        """1 / std of the latent means over training windows, so diffusion sees unit-scale latents."""
        vae.eval()
        b = WindowSampler(self.dataset, self.cfg.data.window, 0.0).batch(n, np.random.default_rng(1234))
        mu, _ = vae.encode(b["features"], b["activation"])
        return float(1.0 / mu.float().std().clamp_min(1e-6))

    def load_weights(self, model: nn.Module, path: Path, continuing: bool = False) -> dict:
        vae, _, _, doc = load_vae(path)
        load_state_strict(model.vae, vae.state_dict(), str(path))
        return doc.get("meta", {})

    def export(self, model: nn.Module, path: Path, meta: dict[str, Any]) -> None:
        vae = model.vae
        was_training = vae.training
        scale = self.latent_scale(vae)
        vae.train(was_training)
        save_vae(path, vae, self.dataset.normalizer, latent_scale=scale,
                 meta={**meta, "train_config": to_dict(self.cfg)})
