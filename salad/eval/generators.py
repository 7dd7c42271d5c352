"""Generators for the T2M protocol built on a Pipeline: the model itself, and the VAE's
reconstruction of the real motions (its ceiling)."""
from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np
import torch

from ..motion.representation import features_to_joints


class ModelGenerator:
    """captions + lengths -> raw 263-d features, batched with per-motion lengths."""

    uses_references = False

    def __init__(self, pipe, steps: int | None = None, sampler: str = "ddim", cfg: float = 7.5, seed: int = 0):
        steps, cfg, sampler, _ = pipe.check_sampling(steps, cfg, sampler)
        self.pipe, self.steps, self.sampler, self.cfg, self.seed = pipe, steps, sampler, cfg, seed
        self.calls = 0

    def describe(self) -> dict:
        """What makes two runs' generations the same (for resuming an evaluation)."""
        if not hasattr(self, "_weights"):
            digest = hashlib.sha256()
            for model in (self.pipe.network(self.sampler), self.pipe.vae):
                for t in model.state_dict().values():
                    digest.update(t.detach().float().cpu().numpy().tobytes())
            self._weights = digest.hexdigest()
        return {"weights_sha256": self._weights, "bf16": self.pipe.bf16, "steps": self.steps,
                "sampler": self.sampler, "cfg": self.cfg, "seed": self.seed, **self.pipe.sampler_settings(self.sampler)}

    def __call__(self, captions: list[str], lengths: list[int]) -> list[np.ndarray]:
        self.calls += 1
        frames = [min(max(16, (n // 4) * 4), self.pipe.canvas_frames) for n in lengths]
        motions = self.pipe.generate_batch(captions, frames, seed=self.seed * 100003 + self.calls,
                                           steps=self.steps, cfg=self.cfg, sampler=self.sampler)
        out = []
        for m, n in zip(motions, lengths):
            f = m.features
            if len(f) < n:      # lengths the protocol asks for that the model cannot make: hold the last pose
                f = np.concatenate([f, np.repeat(f[-1:], n - len(f), axis=0)])
            out.append(f[:n])
        return out


class VAEReconstruction:
    """The real motions passed through the VAE (mean latent): FID and MPJPE of the autoencoder."""

    uses_references = True

    def __init__(self, pipe):
        self.pipe = pipe
        self.errors: list[float] = []

    @torch.no_grad()
    def __call__(self, captions: list[str], lengths: list[int],
                 references: Sequence[np.ndarray] | None = None) -> list[np.ndarray]:
        out = []
        for ref, n in zip(references, lengths):
            f = np.asarray(ref[:n], dtype=np.float32)
            m = (n // 4) * 4
            x = torch.from_numpy(self.pipe.normalizer.normalize(f[:m]))[None].to(self.pipe.device)
            mu, _ = self.pipe.vae.encode(x)
            rec, _ = self.pipe.vae.decode(mu)
            r = self.pipe.normalizer.denormalize(rec[0].cpu().numpy())
            if m < n:
                r = np.concatenate([r, f[m:]])
            j, jr = features_to_joints(f[:m]), features_to_joints(r[:m])
            self.errors.append(float(np.linalg.norm((j - j[:, :1]) - (jr - jr[:, :1]), axis=-1).mean()))
            out.append(r.astype(np.float32))
        return out

    @property
    def mpjpe_m(self) -> float:
        return float(np.mean(self.errors)) if self.errors else float("nan")
