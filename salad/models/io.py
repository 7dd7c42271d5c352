"""Saving and loading trained models (VAE, denoiser) as checkpoint directories."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ..checkpoint import CheckpointError, load_checkpoint, load_state_strict, read_checkpoint_config, save_checkpoint
from ..config import ConfigError, from_dict, to_dict
from ..diffusion.schedule import DiffusionConfig
from ..motion.representation import Normalizer
from .denoiser import Denoiser, DenoiserConfig
from .vae import MotionVAE, VAEConfig


def save_vae(path: str | Path, vae: MotionVAE, normalizer: Normalizer, latent_scale: float,
             meta: dict[str, Any] | None = None) -> Path:
    config = {"vae": to_dict(vae.config), "latent_scale": latent_scale, "feature_dim": normalizer.dim}
    parts = {"vae": vae.state_dict(),
             "stats": {"mean": torch.from_numpy(normalizer.mean), "std": torch.from_numpy(normalizer.std)}}
    return save_checkpoint(path, "vae", config, parts, meta)


def load_vae(path: str | Path) -> tuple[MotionVAE, Normalizer, float, dict]:
    doc, parts = load_checkpoint(path, kind="vae")
    try:
        cfg = from_dict(VAEConfig, doc["config"]["vae"], f"{path}/config.json:vae")
        scale = float(doc["config"]["latent_scale"])
    except (KeyError, ConfigError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: bad VAE config ({e})") from None
    vae = MotionVAE(cfg)
    load_state_strict(vae, parts["vae"], str(path))
    stats = parts["stats"]
    norm = Normalizer(stats["mean"].numpy(), stats["std"].numpy())
    return vae.eval(), norm, scale, doc


def save_denoiser(path: str | Path, denoiser: Denoiser, diffusion: DiffusionConfig, text_encoder: dict,
                  canvas_frames: int, vae_checksum: str, meta: dict[str, Any] | None = None) -> Path:
    config = {"denoiser": to_dict(denoiser.config), "diffusion": to_dict(diffusion), "text_encoder": text_encoder,
              "canvas_frames": canvas_frames, "vae_checksum": vae_checksum}
    return save_checkpoint(path, "denoiser", config, {"denoiser": denoiser.state_dict()}, meta)


def load_denoiser(path: str | Path) -> tuple[Denoiser, dict]:
    doc, parts = load_checkpoint(path, kind="denoiser")
    try:
        cfg = from_dict(DenoiserConfig, doc["config"]["denoiser"], f"{path}/config.json:denoiser")
    except (KeyError, ConfigError, TypeError) as e:
        raise CheckpointError(f"{path}: bad denoiser config ({e})") from None
    model = Denoiser(cfg)
    load_state_strict(model, parts["denoiser"], str(path))
    return model.eval(), doc


def vae_checksum(path: str | Path) -> str:
    """Identifies a VAE checkpoint by its weights file, so a denoiser can check its partner."""
    return read_checkpoint_config(path, kind="vae")["files"]["vae"]["sha256"]
