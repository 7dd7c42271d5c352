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
             meta: dict[str, Any] | None = None, latent_sources: list[str] | None = None) -> Path:
    """latent_sources: checksums of the VAEs whose encoder (and so latent space) this one keeps,
    oldest first (the one whose encoder was trained); a denoiser trained on any of them fits this VAE."""
    config = {"vae": to_dict(vae.config), "latent_scale": latent_scale, "feature_dim": normalizer.dim}
    if latent_sources:
        config["latent_source_sha256"] = latent_sources[0]
        config["latent_lineage_sha256"] = list(latent_sources)
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


def load_consistency_student(path: str | Path) -> tuple[Denoiser, dict, dict]:
    """A consistency-distilled student, its checkpoint document and what it was distilled from
    (meta["consistency"]: guidance range, teacher)."""
    student, doc = load_denoiser(path)
    info = doc.get("meta", {}).get("consistency")
    if not student.config.guidance_embedding or not isinstance(info, dict):
        raise CheckpointError(f"{path}: not a consistency-distilled student (train one with `salad train consistency`)")
    return student, doc, info


def partner_mismatches(config: dict, reference: dict, vae_checksums: set[str]) -> list[str]:
    """What keeps a checkpoint (the "config" of its config.json) from sampling beside the one whose config
    is `reference`: the text features, diffusion or canvas that differ, and "VAE latents" when it records
    a VAE outside `vae_checksums`."""
    bad = [k for k in ("text_encoder", "diffusion", "canvas_frames") if config.get(k) != reference.get(k)]
    if config.get("vae_checksum") and config["vae_checksum"] not in vae_checksums:
        bad.append("VAE latents")
    return bad


def vae_checksum(path: str | Path) -> str:
    """Identifies a VAE checkpoint by its weights file, so a denoiser can check its partner."""
    return read_checkpoint_config(path, kind="vae")["files"]["vae"]["sha256"]


def vae_latent_sources(path: str | Path) -> list[str]:
    """Checksums of the VAEs sharing `path`'s latent space, the oldest first, itself last."""
    doc = read_checkpoint_config(path, kind="vae")
    own = doc["files"]["vae"]["sha256"]
    lineage = doc["config"].get("latent_lineage_sha256") or []
    source = doc["config"].get("latent_source_sha256")
    if not isinstance(lineage, list) or not all(isinstance(c, str) for c in lineage) or \
            (source is not None and not isinstance(source, str)):
        raise CheckpointError(f"{path}/config.json: latent_source_sha256 / latent_lineage_sha256 are malformed")
    chain = ([source] if source else []) + lineage + [own]
    return list(dict.fromkeys(chain))


def vae_latent_origin(path: str | Path) -> str:
    """The checksum that names `path`'s latent space: the VAE whose encoder made it. A denoiser or
    student records this one, so that any decoder fine-tuned on the same frozen encoder fits it,
    a sibling of the VAE it was trained with included."""
    return vae_latent_sources(path)[0]


def vae_latent_checksums(path: str | Path) -> set[str]:
    """The VAE checksums a denoiser may have recorded and still fit this VAE: its own, or that of
    a VAE it was fine-tuned from with the encoder frozen."""
    return set(vae_latent_sources(path))
