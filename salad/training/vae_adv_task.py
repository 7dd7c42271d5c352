"""Adversarial (SAN) fine-tuning of a trained VAE's decoder, keeping its latent space (MoLA §3.2).

The encoder and the latent scale are frozen, so a denoiser trained on the source VAE's latents
decodes through the fine-tuned decoder unchanged; the exported checkpoint records the source's
checksum for load_pipeline's compatibility check. The decoder minimises the source VAE's own
reconstruction loss plus lambda_adv times the SAN generator loss (plus, where set, lambda_foot and
lambda_root times the feet's and the root's world-velocity errors, lambda_acc times the joints'
acceleration error and lambda_bone times the bone lengths' error: training/foot_loss.py); the
discriminator learns from the same batch. Both updates come from one backward pass through the shared Trainer
(exact resume, bf16): the discriminator sees the reconstruction detached, and the decoder's
adversarial term sees the discriminator's parameters detached, so each loss reaches only
its own player.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
from torch.func import functional_call

from ..config import ConfigError, to_dict, validate
from ..data.dataset import MotionDataset, WindowSampler
from ..models.discriminator import SANDiscriminator, san_discriminator_loss, san_generator_loss
from ..models.io import load_vae, save_vae, vae_latent_sources
from ..models.vae import ENCODER_PARTS, MotionVAE, widen_decoder
from ..motion.representation import Normalizer
from .balance import window_weights
from .configs import VAESANTrainConfig
from .denoised_latents import DenoisedLatents
from .foot_loss import bone_error, velocity_errors


def encoder_modules(vae: MotionVAE) -> list[nn.Module]:
    return [getattr(vae, name) for name in ENCODER_PARTS]


def encoder_state(vae: MotionVAE) -> dict[str, torch.Tensor]:
    """The encoder's weights (what defines the latent space), keyed as in vae.state_dict()."""
    return {k: v for k, v in vae.state_dict().items() if k.split(".", 1)[0] in ENCODER_PARTS}


class AdversarialVAETraining(nn.Module):
    """forward(batch) -> (loss, logs) for the Trainer; encoder frozen and always in eval mode."""

    def __init__(self, vae: MotionVAE, discriminator: SANDiscriminator, lambda_adv: float,
                 lambda_foot: float = 0.0, normalizer: Normalizer | None = None, lambda_root: float = 0.0,
                 lambda_acc: float = 0.0, lambda_bone: float = 0.0):
        super().__init__()
        if min(lambda_adv, lambda_foot, lambda_root, lambda_acc, lambda_bone) < 0:
            raise ValueError(f"lambda_adv, lambda_foot, lambda_root, lambda_acc and lambda_bone must be >= 0, got "
                             f"{lambda_adv}, {lambda_foot}, {lambda_root}, {lambda_acc} and {lambda_bone}")
        if max(lambda_foot, lambda_root, lambda_acc, lambda_bone) > 0 and normalizer is None:
            raise ValueError("lambda_foot, lambda_root, lambda_acc and lambda_bone need the VAE's normalizer "
                             "(the terms work in metres)")
        self.vae, self.disc, self.lambda_adv = vae, discriminator, float(lambda_adv)
        self.lambda_foot, self.lambda_root, self.normalizer = float(lambda_foot), float(lambda_root), normalizer
        self.lambda_acc, self.lambda_bone = float(lambda_acc), float(lambda_bone)
        for m in encoder_modules(vae):
            m.requires_grad_(False)

    def train(self, mode: bool = True):
        super().train(mode)
        # the denoiser's latents come from the encoder in eval mode (no dropout): train the
        # decoder on exactly those
        for m in encoder_modules(self.vae):
            m.eval()
        return self

    def forward(self, batch: dict):
        x, act = batch["features"], batch["activation"]
        valid = act > 0.5
        total, logs, recon, _ = self.vae.loss(x, act, valid=valid, eps=batch["eps"], z_given=batch.get("z_given"),
                                              given_rows=batch.get("given_rows"))
        logs["rec_total"] = logs.pop("total")
        kinematic = 0.0
        if max(self.lambda_foot, self.lambda_root, self.lambda_acc) > 0:
            errs = velocity_errors(recon, x, valid, self.normalizer)
            total = total + self.lambda_foot * errs["foot"] + self.lambda_root * errs["root"] + self.lambda_acc * errs["accel"]
            logs.update(foot=float(errs["foot"].detach()), root_vel=float(errs["root"].detach()),
                        accel=float(errs["accel"].detach()))
            kinematic = self.lambda_foot * logs["foot"] + self.lambda_root * logs["root_vel"] + self.lambda_acc * logs["accel"]
        if self.lambda_bone > 0:
            bones = bone_error(recon, x, valid, self.normalizer)
            total = total + self.lambda_bone * bones
            logs["bone"] = float(bones.detach())
            kinematic = kinematic + self.lambda_bone * logs["bone"]
        if self.lambda_adv > 0:
            mask = self.disc.patch_mask(valid)
            frozen = {k: v.detach() for k, v in self.disc.named_parameters()}
            g_adv = san_generator_loss(functional_call(self.disc, frozen, (recon, valid)), mask)
            d_loss, d_logs = san_discriminator_loss(self.disc.san_logits(x, valid),
                                                    self.disc.san_logits(recon.detach(), valid), mask)
            total = total + self.lambda_adv * g_adv + d_loss
            logs.update(d_logs, g_adv=float(g_adv.detach()), d_loss=float(d_loss.detach()))
        logs["loss"] = logs["rec_total"] + self.lambda_adv * logs.get("g_adv", 0.0) + kinematic
        return total, logs


class VAESANTask:
    kind = "vae-san"

    def __init__(self, cfg: VAESANTrainConfig, dataset: MotionDataset | None = None):
        self.cfg = cfg
        validate(cfg)
        vae, self.normalizer, self.latent_scale, _ = load_vae(cfg.vae)
        if cfg.decoder_dim and cfg.decoder_dim != vae.decoder_dim:
            if cfg.decoder_dim < vae.decoder_dim:
                raise ConfigError(f"decoder_dim {cfg.decoder_dim} is narrower than {cfg.vae}'s decoder "
                                  f"({vae.decoder_dim}); 0 keeps it")
            vae = widen_decoder(vae, cfg.decoder_dim, seed=cfg.run.seed)
        self.sources = vae_latent_sources(cfg.vae)
        # the source VAE's statistics define its latent space, whatever the data directory holds
        self.dataset = dataset or MotionDataset(cfg.data.root, "train", min_frames=cfg.data.min_frames,
                                                max_frames=10 ** 9, normalizer=self.normalizer,
                                                require_captions=False)
        if self.dataset.dim != self.normalizer.dim:
            raise ValueError(f"{cfg.data.root}: {self.dataset.dim}-d features, but the VAE {cfg.vae} "
                             f"expects {self.normalizer.dim}")
        if cfg.discriminator.feature_dim != self.normalizer.dim:
            raise ValueError(f"discriminator.feature_dim is {cfg.discriminator.feature_dim}, "
                             f"the data has {self.normalizer.dim} dims")
        weights = window_weights(self.dataset, cfg.data.balance)
        self.sampler = WindowSampler(self.dataset, cfg.data.window, cfg.window_overhang, weights)
        self.denoised = DenoisedWindows(cfg.denoised_latents, self.dataset, cfg.data.window, self.sources[0],
                                        weights) if cfg.denoised_latents else None
        torch.manual_seed(cfg.run.seed)
        self.model = AdversarialVAETraining(vae, SANDiscriminator(cfg.discriminator), cfg.lambda_adv,
                                            cfg.lambda_foot, self.normalizer, cfg.lambda_root, cfg.lambda_acc,
                                            cfg.lambda_bone)

    def batch(self, rng: np.random.Generator) -> dict:
        size = self.cfg.optim.batch_size
        given = round(size * self.cfg.denoised_share) if self.denoised is not None else 0
        b = self.sampler.batch(size - given, rng)
        if given:
            d = self.denoised.batch(given, rng)
            rows = torch.zeros(size, dtype=torch.bool)
            rows[size - given:] = True
            z = torch.zeros(size, *d["z_given"].shape[1:])
            z[size - given:] = d["z_given"]
            b = {"features": torch.cat((b["features"], d["features"])),
                 "activation": torch.cat((b["activation"], d["activation"])), "z_given": z, "given_rows": rows}
        B, T = b["activation"].shape
        g = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        b["eps"] = torch.randn(B, T // 4, 7, self.model.vae.config.latent_dim, generator=g)
        return b

    def loss(self, model: nn.Module, batch: dict):
        return model(batch)

    def config_dict(self) -> dict:
        # the source's checksum is part of the run's identity: resuming against a different
        # VAE at the same path must fail
        return {**to_dict(self.cfg), "source_vae_sha256": self.sources[-1]}

    def export(self, model: nn.Module, path: Path, meta: dict[str, Any]) -> None:
        save_vae(path, model.vae, self.normalizer, latent_scale=self.latent_scale,
                 meta={**meta, "train_config": to_dict(self.cfg)}, latent_sources=self.sources)


class DenoisedWindows:
    """Training windows of real clips paired with the same window of their denoised latent, each clip
    drawn as often as item_weights (per dataset item, window_weights) draws it among the real windows, or
    every clip alike without them."""

    def __init__(self, path: str, dataset: MotionDataset, window: int, latent_origin: str,
                 item_weights: np.ndarray | None = None):
        d = DenoisedLatents(path)
        if d.latent_origin != latent_origin:
            raise ConfigError(f"{path} was made in another latent space (VAE {d.latent_origin[:12]}, "
                              f"this decoder's encoder is {latent_origin[:12]}): build it again from this model")
        index = {it.name: i for i, it in enumerate(dataset.items)}
        missing = [n for n in d.names if n not in index]
        if missing:
            raise ConfigError(f"{path}: {len(missing)} clips are not in the training data, e.g. {missing[0]!r}")
        self.d, self.ds, self.window = d, dataset, window
        self.pairs = [(k, index[n]) for k, n in enumerate(d.names) if 4 * len(d.latent(k)) >= window]
        if not self.pairs:
            raise ConfigError(f"{path}: no clip is {window} frames long")
        # half of a batch drawn clip by clip would show a one-take action about once in 1,400 windows
        # where data.balance asks for one in 24 (Bandai's kick): the rare actions' peaks then go unlearnt
        self.p = None
        if item_weights is not None:
            w = np.asarray([item_weights[i] for _, i in self.pairs], dtype=np.float64)
            self.p = w / w.sum()

    def batch(self, size: int, rng: np.random.Generator) -> dict:
        W, w = self.window, self.window // 4
        feats = np.zeros((size, W, self.ds.dim), dtype=np.float32)
        z = []
        draws = rng.integers(0, len(self.pairs), size=size) if self.p is None else \
            rng.choice(len(self.pairs), size=size, p=self.p)
        for b, p in enumerate(draws):
            k, item = self.pairs[p]
            latent = self.d.latent(k)
            s = int(rng.integers(0, len(latent) - w + 1))
            feats[b] = self.ds.normalizer.normalize(self.ds.items[item].features[4 * s:4 * s + W])
            z.append(latent[s:s + w])
        return {"features": torch.from_numpy(feats), "activation": torch.ones(size, W), "z_given": torch.stack(z)}


def train_vae_san(a) -> int:
    """`salad train vae-san --config configs/vae_san.toml [--init-from VAE_DIR]`: --init-from
    names the VAE to fine-tune (overrides the config's `vae`)."""
    from ..config import apply_overrides, load_toml
    from .loop import Trainer

    cfg = load_toml(VAESANTrainConfig, a.config)
    apply_overrides(cfg, a)
    if getattr(a, "init_from", None):
        cfg.vae = a.init_from
    out = Trainer(VAESANTask(cfg), cfg.optim, cfg.run).fit()
    print(f"model written to {out}")
    return 0
