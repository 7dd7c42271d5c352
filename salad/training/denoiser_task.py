"""Training task for the latent denoiser.

Each batch is either "fixed length" (motions of their own length, padded and masked
in time) or "auto length" (every motion on the full canvas, followed by VAE-encoded
padding whose activation channel is 0), chosen per batch. One model thus learns both
to fill a requested duration and to decide a duration itself (MoLA). Latents are samples
of the frozen VAE's posterior (or its means, with posterior_noise = 0): encoded at first use
for motions that fit the canvas, at every use for random windows of longer ones.

With contact_loss > 0 the clean-latent estimate is also decoded by the frozen VAE and its
planted feet are held to the real motion's (training/foot_loss.py), weighted per sample by the
signal share at t: at high noise the estimate is a blur of many motions, and pinning its feet
there would fight the diffusion objective.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm

from ..config import ConfigError, to_dict, validate
from ..data.dataset import MotionDataset
from ..diffusion.schedule import NoiseSchedule
from ..models.denoiser import Denoiser
from ..checkpoint import CheckpointError, load_state_strict
from .balance import class_weights, dataset_content
from ..models.io import load_denoiser, load_vae, save_denoiser, vae_latent_checksums, vae_latent_origin
from ..models.widen import widen, widened_config
from ..models.text import load_text_encoder, parse_text_encoder_spec
from ..models.text_bank import TextBank, cached_text_bank
from ..precision import resolve_device
from .configs import DenoiserTrainConfig
from .foot_loss import planted_foot_error
from .latent_bundle import LatentBundle


FRAME_BUCKET = 16     # fixed-length batches span a multiple of 16 frames (4 latent frames), masked past the longest
TOKEN_BUCKET = 8      # and a multiple of 8 caption tokens
TEXT_CACHE = ".salad-cache"   # under data.root: the captions' text features, encoded once per encoder


class DenoiserTraining(nn.Module):
    def __init__(self, denoiser: Denoiser, schedule: NoiseSchedule, min_snr_gamma: float = 0.0):
        super().__init__()
        self.denoiser = denoiser
        self.schedule = schedule
        self.min_snr_gamma = min_snr_gamma

    def snr_weights(self, t: torch.Tensor) -> torch.Tensor:
        """Min-SNR-gamma weights (Hang et al. 2023) of timesteps t: the loss of each prediction type
        rescaled to that of the clean sample, capped at gamma, so the nearly clean timesteps, whose
        targets are easy, stop dominating the gradient."""
        a = self.schedule.alphas_cumprod.to(t.device)[t.long()]
        snr = (a / (1.0 - a)).float()
        capped = snr.clamp(max=self.min_snr_gamma)
        kind = self.schedule.config.prediction_type
        return capped / (snr + 1.0) if kind == "v_prediction" else capped / snr if kind == "epsilon" else capped

    def forward(self, batch: dict, weighted: bool = True, anchor: Denoiser | None = None):
        """(loss, logs, the clean-latent estimate); weighted=False leaves out the min-SNR weights, so
        losses of runs with and without them compare. With an anchor, the rows not marked in
        batch["learn"] are held to the anchor's prediction instead of the data's target."""
        z0 = batch["latents"]
        t = batch["timesteps"]
        noise = batch["noise"]
        zt = self.schedule.add_noise(z0, noise, t)
        inputs = (zt, t, batch["text"], batch["text_mask"], batch["frame_mask"])
        pred = self.denoiser(*inputs, pooled_text=batch["pooled"], auto_length=batch["auto"])
        target = self.schedule.target(z0, noise, t)
        logs = {}
        if anchor is not None and "learn" in batch:
            learn = batch["learn"]
            with torch.no_grad():
                held = anchor(*inputs, pooled_text=batch["pooled"], auto_length=batch["auto"])
            target = torch.where(learn[:, None, None, None], target.float(), held.float())
            logs["learn"] = float(learn.float().mean())
        err = F.mse_loss(pred.float(), target.float(), reduction="none").mean(dim=(2, 3))  # (B, T)
        if self.min_snr_gamma > 0 and weighted:
            err = err * self.snr_weights(t)[:, None]
        if batch["frame_mask"] is not None:
            w = batch["frame_mask"].float()
            loss = (err * w).sum() / w.sum().clamp_min(1.0)
        else:
            loss = err.mean()
        x0, _ = self.schedule.to_x0_eps(zt.float(), pred.float(), t)
        return loss, {"loss": float(loss.detach()), "auto": float(batch["auto"].float().mean()), **logs}, x0


class DenoiserTask:
    kind = "denoiser"
    # --new-latents: a warm start may come from a denoiser of another latent space (its VAE's
    # encoder since retrained); the weights are a start, not a partner, so no identity check
    new_latents = False

    def __init__(self, cfg: DenoiserTrainConfig, show_progress: bool = True, encode_text: bool = True):
        """encode_text=False loads the text encoder without encoding the captions (self.text is None):
        for a bundle that stores the encoder's cut tower instead of the features."""
        self.cfg = cfg
        try:
            self.vae, self.normalizer, self.latent_scale, _ = load_vae(cfg.vae)
        except CheckpointError as e:
            raise CheckpointError(f"the denoiser's VAE: {e} (train one with `salad train vae`, or pass "
                                  "--vae assets/model/vae to use the embedded one)") from None
        self.vae.requires_grad_(False)
        self.vae_checksum = vae_latent_origin(cfg.vae)
        d = cfg.data
        self.canvas = (d.max_frames // 4) * 4
        # VAE posteriors (mean, log-variance) over the canvas of motions that fit it, kept from
        # their first draw: the encoder is frozen and their input never changes, and the batched
        # encode was ~15% of a step (the cache grows to ~0.4 GB on the Bandai build). Longer
        # motions get a random window, encoded each time.
        self._posteriors: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        validate(cfg)        # before minutes of loading
        self.bundle = None
        self._validation: list[dict] | None = None
        if d.bundle:
            self._from_bundle(cfg)
        else:
            self.dataset = MotionDataset(d.root, "train", min_frames=d.min_frames, max_frames=d.max_frames,
                                         normalizer=self.normalizer)
            self.lengths = np.array([len(it.features) for it in self.dataset.items], dtype=np.int64)
            self.captions = [list(it.captions) for it in self.dataset.items]
            self.content = dataset_content(self.dataset) if d.balance != 1.0 or cfg.anchor else None
            self.text_encoder = load_text_encoder(cfg.text_encoder)
            self.text_spec = self.text_encoder.spec()
            if cfg.model.text_dim != self.text_encoder.dim:
                raise ValueError(f"model.text_dim is {cfg.model.text_dim} but the {self.text_encoder.name} "
                                 f"text encoder gives {self.text_encoder.dim}-d features")
            self.text = (cached_text_bank(self.text_encoder, [c for cs in self.captions for c in cs],
                                          Path(d.root) / TEXT_CACHE, progress=show_progress, dtype=torch.bfloat16)
                         if encode_text else None)
        self._by_length = np.argsort(np.minimum(self.lengths, self.canvas), kind="stable")
        self.draw_weights = class_weights(self.content, d.balance)     # per motion; None: uniform
        self.schedule = NoiseSchedule(cfg.diffusion)
        torch.manual_seed(cfg.run.seed)
        self.model = DenoiserTraining(Denoiser(cfg.model), self.schedule, cfg.min_snr_gamma)
        self.anchor, self._learn = self._load_anchor(cfg) if cfg.anchor else (None, None)

    def _load_anchor(self, cfg: DenoiserTrainConfig) -> tuple[Denoiser, np.ndarray]:
        """The frozen anchor (cfg.anchor) and, per training motion, whether it learns from the data
        (its content class has at most anchor_max_clips clips) rather than from the anchor."""
        rare = self.rare_motions(cfg.anchor_max_clips, "anchor", "held to the anchor")
        anchor = Denoiser(cfg.model)
        self._load_checked(anchor, Path(cfg.anchor))
        return anchor.eval().requires_grad_(False), rare

    def rare_motions(self, max_clips: int, name: str, other: str) -> np.ndarray:
        """Per training motion, whether its content class has at most `max_clips` clips; `name` (the
        setting) and `other` (what the other classes' rows get) word the error where that splits nothing."""
        _, cls, counts = np.unique(self._content_of_motions(name), return_inverse=True, return_counts=True)
        rare = counts <= max_clips
        if rare.all() or not rare.any():
            raise ConfigError(f"{name}_max_clips = {max_clips} leaves {'no' if rare.all() else 'every'} content "
                              f"class {other} (clips per class: {min(counts)}-{max(counts)}); choose a count between")
        return rare[cls]

    def class_motions(self, classes: list[str], name: str) -> np.ndarray:
        """Per training motion, whether its content class is one of `classes` (`name`: the setting)."""
        content = np.asarray(self._content_of_motions(name))
        known = set(content.tolist())
        unknown = sorted(set(classes) - known)
        if unknown:
            raise ConfigError(f"{name}_classes names {unknown}, which no training motion has; the content classes "
                              f"are {', '.join(sorted(known))}")
        return np.isin(content, classes)

    def classes_of(self, motions: np.ndarray | None) -> list[str]:
        """The content classes of the training motions marked in `motions` (rare_motions, class_motions)."""
        if motions is None:
            return []
        return sorted(set(np.asarray(self._content_of_motions("focus"))[motions].tolist()))

    def _content_of_motions(self, name: str):
        content = self.content
        if content is None and self.bundle is None:
            try:
                content = dataset_content(self.dataset)
            except ConfigError:
                content = None
        if content is None:
            raise ConfigError(f"{name} picks actions by their content class, and this data has no content labels")
        return content

    def _from_bundle(self, cfg: DenoiserTrainConfig) -> None:
        """Motions, latents and text features from a latent bundle (salad data bundle) instead
        of the dataset and the text encoder."""
        if cfg.posterior_noise != 0.0 or cfg.contact_loss > 0:
            raise ConfigError("a latent bundle holds the posterior means alone: training from data.bundle needs "
                              "posterior_noise = 0 and contact_loss = 0 (train on data.root for the others)")
        self.bundle = b = LatentBundle(cfg.data.bundle, resolve_device(cfg.run.device))
        if b.vae_checksum not in vae_latent_checksums(cfg.vae):
            raise ConfigError(f"{cfg.data.bundle} holds another VAE's latents than {cfg.vae}'s")
        if b.canvas != self.canvas or abs(b.latent_scale - self.latent_scale) > 1e-6:
            raise ConfigError(f"{cfg.data.bundle}: made for a {b.canvas}-frame canvas at latent scale "
                              f"{b.latent_scale:.6g}; this config has {self.canvas} frames (data.max_frames) and the "
                              f"VAE scale {self.latent_scale:.6g}")
        want = parse_text_encoder_spec(cfg.text_encoder)
        if (any(b.text_spec.get(k) != want[k] for k in ("kind", "arch") if k in want)
                or b.text_spec.get("dim") != cfg.model.text_dim):
            raise ConfigError(f"{cfg.data.bundle} holds {b.text_spec.get('name')} text features "
                              f"({b.text_spec.get('dim')}-d); this config uses {cfg.text_encoder} with "
                              f"model.text_dim = {cfg.model.text_dim}")
        self.lengths, self.captions, self.content = b.lengths, b.captions, b.content
        self.text, self.text_spec, self.text_encoder = b.text, b.text_spec, None

    # ------------------------------------------------------------ batches
    def _canvas(self, crops: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised motions placed on the canvas, followed by padding with activation 0."""
        feats = torch.zeros(len(crops), self.canvas, self.dataset.dim)
        act = torch.zeros(len(crops), self.canvas)
        for b, c in enumerate(crops):
            feats[b, :len(c)] = torch.from_numpy(c)
            act[b, :len(c)] = 1.0
        return feats, act

    @torch.no_grad()
    def encode(self, crops: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """The VAE posterior (mean, log-variance) of raw feature crops, each on the canvas followed by padding."""
        return self.vae.encode(*self._canvas([self.normalizer.normalize(c) for c in crops]))

    def _crop(self, feats: np.ndarray, rng: np.random.Generator, max_len: int) -> np.ndarray:
        if len(feats) > max_len:
            s = int(rng.integers(0, len(feats) - max_len + 1))
            feats = feats[s:s + max_len]
        return feats[: (len(feats) // 4) * 4]

    def batch(self, rng: np.random.Generator, first: np.ndarray | None = None) -> dict:
        """A training batch; `first`: motions that take its first rows, whatever the draw gave them."""
        B = self.cfg.optim.batch_size
        auto = bool(rng.random() < self.cfg.auto_length_prob) if self.cfg.model.length_modes else False
        w, span = self.draw_weights, min(len(self._by_length), 4 * B)
        if auto:
            idx = rng.integers(0, len(self.lengths), size=B) if w is None else rng.choice(len(w), size=B, p=w)
        elif w is None:
            # Fixed-length batches draw motions of similar length (a random window of the
            # length-sorted list), so padding, which costs as much as motion, stays small.
            start = int(rng.integers(0, len(self._by_length) - span + 1))
            idx = self._by_length[start + rng.integers(0, span, size=B)]
        else:
            # the window is centred on a motion drawn by weight, and drawn from by weight
            centre = int(rng.choice(len(w), p=w[self._by_length]))
            start = min(max(centre - span // 2, 0), len(self._by_length) - span)
            window = self._by_length[start:start + span]
            idx = window[rng.choice(span, size=B, p=w[window] / w[window].sum())]
        if first is not None:
            idx[: len(first)] = first
        # Every motion is encoded followed by padding with activation 0 (the way the VAE saw
        # motion ends in training) on the whole canvas; fixed-length rows then keep only their
        # own latent frames (masked in time), auto-length rows keep the whole canvas.
        frames = np.where(self.lengths[idx] <= self.canvas, self.lengths[idx] // 4 * 4, self.canvas)
        # Batch shapes come from a few buckets: on the CPU each new (frames, tokens) shape adds kernel
        # primitives and allocator pools, and with one shape per length a long run's memory kept growing.
        T = self.canvas if auto else min(self.canvas, -(-int(frames.max()) // FRAME_BUCKET) * FRAME_BUCKET)
        if self.bundle is not None:
            latents, crops = self.bundle.rows(idx, rng) * self.latent_scale, None
        else:
            latents, crops = self._dataset_latents(idx, rng)
        latents = latents[:, : T // 4]
        if auto:
            frame_mask = None
        else:
            frame_mask = torch.arange(T // 4)[None, :] < torch.as_tensor(frames // 4)[:, None]
            latents = latents * frame_mask[:, :, None, None]
        captions = [self.captions[i][int(rng.integers(len(self.captions[i])))] for i in idx]
        drop = rng.random(B) < self.cfg.text_dropout
        captions = ["" if d else c for c, d in zip(captions, drop)]
        text, text_mask, pooled = self.text.batch(captions, TOKEN_BUCKET)
        g = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        extra = {}
        if self.cfg.contact_loss > 0:
            # the real motions, normalised, on the rows' frames (what the decoded estimate is held to)
            feats, act = self._canvas([self.normalizer.normalize(c[:T]) for c in crops])
            extra = {"features": feats[:, :T], "valid": act[:, :T] > 0.5}
        if self._learn is not None:
            extra["learn"] = torch.from_numpy(self._learn[idx])
        return {**extra, "rows": torch.from_numpy(idx), "latents": latents, "frame_mask": frame_mask, "text": text,
                "text_mask": text_mask, "pooled": pooled, "captions": captions, "auto": torch.full((B,), auto),
                "timesteps": torch.randint(0, self.schedule.config.train_steps, (B,), generator=g),
                "noise": torch.randn(latents.shape, generator=g)}

    def text_features(self, captions: list[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Tokens, mask and pooled features of captions as a batch carries them: the bank's, or, where
        some are not training captions, the text encoder's (its tokens rounded to the bank's bf16)."""
        if all(c in self.text.index for c in captions):
            return self.text.batch(captions, TOKEN_BUCKET)
        if self.text_encoder is None:
            raise ConfigError("captions outside the training set need the text encoder, and a latent bundle "
                              "holds only its own captions' features")
        f = self.text_encoder.encode(list(captions))
        pad = -f.tokens.shape[1] % TOKEN_BUCKET
        tokens = F.pad(f.tokens, (0, 0, 0, pad)).to(torch.bfloat16).float()
        return tokens.cpu(), F.pad(f.mask, (0, pad)).cpu(), f.pooled.float().cpu()

    def _dataset_latents(self, idx: np.ndarray, rng: np.random.Generator) -> tuple[torch.Tensor, list[np.ndarray]]:
        """Scaled latents on the canvas of motions `idx` (posterior samples at posterior_noise), and
        the feature crops they encode."""
        items = [self.dataset.items[i] for i in idx]
        fits = [len(it.features) <= self.canvas for it in items]
        crops = [it.features[: (len(it.features) // 4) * 4] if ok else self._crop(it.features, rng, self.canvas)
                 for it, ok in zip(items, fits)]
        posterior = {b: self._posteriors[int(i)] for b, i in enumerate(idx) if int(i) in self._posteriors}
        todo = [b for b in range(len(idx)) if b not in posterior]
        if todo:
            mu, logvar = self.encode([crops[b] for b in todo])
            for k, b in enumerate(todo):
                posterior[b] = (mu[k].clone(), logvar[k].clone())
                if fits[b]:
                    self._posteriors[int(idx[b])] = posterior[b]
        mu = torch.stack([posterior[b][0] for b in range(len(idx))])
        logvar = torch.stack([posterior[b][1] for b in range(len(idx))])
        noise = self.cfg.posterior_noise * torch.randn_like(mu) * torch.exp(0.5 * logvar)
        return (mu + noise) * self.latent_scale, crops

    # ------------------------------------------------------------ validation
    def validation_loss(self, model: nn.Module) -> float | None:
        """The unweighted diffusion loss over the validation split, each motion once (its start on
        the canvas, its first caption, the posterior mean) at fixed timesteps and noise, so that the
        numbers of runs with other recipes (data weighting, min-SNR, learning rate) compare. None
        for a latent bundle, which holds the training split alone."""
        if self.bundle is not None:
            return None
        if self._validation is None:
            self._validation = self._validation_batches()
        device = next(model.parameters()).device
        total = rows = 0.0
        for batch in self._validation:
            loss, _, _ = model({k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()},
                               weighted=False)
            n = float(batch["frame_mask"].sum())
            total, rows = total + float(loss) * n, rows + n
        return total / rows

    def _validation_batches(self) -> list[dict]:
        d = self.cfg.data
        val = MotionDataset(d.root, "val", min_frames=d.min_frames, max_frames=d.max_frames,
                            normalizer=self.normalizer)
        # by length, so that each batch pads little
        items = sorted(val.items, key=lambda it: min(len(it.features), self.canvas))
        crops = [it.features[: min(len(it.features), self.canvas) // 4 * 4] for it in items]
        captions = [it.captions[0] for it in items]
        bank = TextBank(self.text_encoder, captions, progress=False, dtype=torch.bfloat16)
        g = torch.Generator().manual_seed(12345)
        B, batches = self.cfg.optim.batch_size, []
        for s in range(0, len(crops), B):
            part = crops[s:s + B]
            mu, _ = self.encode(part)
            frames = torch.tensor([len(c) for c in part])
            T = min(self.canvas, -(-int(frames.max()) // FRAME_BUCKET) * FRAME_BUCKET)
            frame_mask = torch.arange(T // 4)[None, :] < (frames // 4)[:, None]
            latents = mu[:, : T // 4] * self.latent_scale * frame_mask[:, :, None, None]
            text, text_mask, pooled = bank.batch(captions[s:s + B], TOKEN_BUCKET)
            batches.append({"latents": latents, "frame_mask": frame_mask, "text": text, "text_mask": text_mask,
                            "pooled": pooled, "auto": torch.zeros(len(part), dtype=torch.bool),
                            "timesteps": torch.randint(0, self.schedule.config.train_steps, (len(part),), generator=g),
                            "noise": torch.randn(latents.shape, generator=g)})
        return batches

    def loss(self, model: nn.Module, batch: dict):
        if self.anchor is not None:
            self.anchor.to(batch["latents"].device)
        loss, logs, x0 = model(batch, anchor=self.anchor)
        if self.cfg.contact_loss > 0:
            feet = self.foot_error(x0, batch)
            logs["foot"] = float(feet.detach())
            loss = loss + self.cfg.contact_loss * feet
        return loss, logs

    def foot_error(self, x0: torch.Tensor, batch: dict) -> torch.Tensor:
        """planted_foot_error of the decoded clean estimates, each row weighted by alpha_bar(t)."""
        recon, _ = self.vae.to(x0.device).decode(x0 / self.latent_scale)
        signal = self.schedule.alphas_cumprod.to(x0.device)[batch["timesteps"].long()].float()
        return planted_foot_error(recon, batch["features"], batch["valid"], self.normalizer, weights=signal)

    def config_dict(self) -> dict:
        return to_dict(self.cfg)

    def load_weights(self, model: nn.Module, path: Path, continuing: bool = False) -> dict:
        return self._load_checked(model.denoiser, path)

    def _load_checked(self, into: Denoiser, path: Path) -> dict:
        denoiser, doc = load_denoiser(path)
        # Same-shaped weights from another latent space or text encoder would load fine and
        # train into nonsense, so the partners are checked by identity, not by shape.
        trained_on = doc["config"].get("vae_checksum")
        if trained_on and trained_on not in vae_latent_checksums(self.cfg.vae) and not self.new_latents:
            raise CheckpointError(f"{path} was trained on another VAE's latents than {self.cfg.vae}'s; "
                                  "pass the VAE it was trained with (--vae), or --new-latents to re-train it "
                                  "onto this VAE's latent space")
        theirs, mine = doc["config"].get("text_encoder", {}), self.text_spec
        if theirs.get("name") != mine.get("name"):
            raise CheckpointError(f"{path} was trained with the {theirs.get('name')} text encoder, this config "
                                  f"uses {mine.get('name')}")
        if denoiser.config != into.config and widened_config(denoiser.config) == into.config:
            denoiser = widen(denoiser)
            tqdm.write(f"{path}: widened from d = {denoiser.config.dim // 2} to {denoiser.config.dim}, "
                       "computing what it computed", file=sys.stderr)
        load_state_strict(into, denoiser.state_dict(), str(path))
        return doc.get("meta", {})

    def export(self, model: nn.Module, path: Path, meta: dict[str, Any]) -> None:
        save_denoiser(path, model.denoiser, self.schedule.config, self.text_spec, self.canvas,
                      self.vae_checksum, meta={**meta, "train_config": to_dict(self.cfg),
                                               "latent_scale": self.latent_scale})
