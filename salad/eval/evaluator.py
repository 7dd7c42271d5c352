"""The text-motion matching evaluator: a motion encoder and a text encoder trained into a joint space.

Differences from Guo et al. (CVPR 2022), whose protocol the metrics follow:

* text side: frozen MiniLM token features read by a trainable BiGRU, instead of GloVe word vectors plus
  part-of-speech one-hots (GloVe is not available here);
* training: symmetric InfoNCE with a learned temperature instead of Guo's margin loss on shuffled pairs. Every
  other item of a batch serves as a negative (Guo's loss sees one shuffled negative per item), which trains in
  minutes on a CPU. Captions generated from labels repeat, so items with the same labels are targets, not
  negatives (see `contrastive_loss`);
* embeddings are L2-normalised, so distances lie in [0, 2] and FID, Diversity and MM-Dist are on a smaller
  scale than numbers reported with Guo's unnormalised evaluators. Rankings by distance equal rankings by cosine.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..config import ConfigError
from ..motion.representation import FEATURE_DIM
from .networks import (CONTACT_CHANNELS, DOWNSAMPLE, MotionEncoder, MotionEncoderConfig, TextEncoderHead,
                       TextHeadConfig, load_scorer, save_scorer)

KIND = "evaluator"
MAX_LOGIT_SCALE = 100.0


@dataclass
class EvaluatorConfig:
    motion: MotionEncoderConfig = field(default_factory=MotionEncoderConfig)
    text: TextHeadConfig = field(default_factory=TextHeadConfig)
    text_encoder: str = "minilm"
    init_temperature: float = 0.07

    def __post_init__(self) -> None:
        if self.motion.output_dim != self.text.output_dim:
            raise ConfigError(f"motion and text embeddings must have the same width, got "
                              f"{self.motion.output_dim} and {self.text.output_dim}")
        if self.motion.input_dim != FEATURE_DIM - CONTACT_CHANNELS:
            raise ConfigError(f"motion.input_dim must be {FEATURE_DIM - CONTACT_CHANNELS} (263 minus foot contacts)")
        if not 0.0 < self.init_temperature < 1.0:
            raise ConfigError(f"init_temperature must be in (0, 1), got {self.init_temperature}")


def contrastive_loss(text: torch.Tensor, motion: torch.Tensor, logit_scale: torch.Tensor,
                     groups: torch.Tensor | None = None) -> torch.Tensor:
    """Symmetric InfoNCE between unit-norm text and motion embeddings (B, D).

    With `groups`, every pair in the same group is a positive: the target distribution spreads evenly over
    them instead of treating a motion with the very same labels as a negative.
    """
    logits = logit_scale * text @ motion.T
    if groups is None:
        target = torch.eye(len(text), device=text.device)
    else:
        target = (groups[:, None] == groups[None, :]).to(text.dtype)
    target = target / target.sum(1, keepdim=True)
    t2m = -(target * F.log_softmax(logits, dim=1)).sum(1).mean()
    m2t = -(target * F.log_softmax(logits.T, dim=1)).sum(1).mean()
    return 0.5 * (t2m + m2t)


class TextMotionMatcher(nn.Module):
    """The trainable part: motion encoder, text head and temperature."""

    def __init__(self, cfg: EvaluatorConfig):
        super().__init__()
        self.cfg = cfg
        self.motion = MotionEncoder(cfg.motion)
        self.text = TextEncoderHead(cfg.text)
        self.logit_scale = nn.Parameter(torch.tensor(math.log(1.0 / cfg.init_temperature)))

    def encode_motion(self, motion: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.motion(motion, lengths), dim=-1)

    def encode_text(self, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.text(tokens, mask), dim=-1)

    def scale(self) -> torch.Tensor:
        return self.logit_scale.clamp(max=math.log(MAX_LOGIT_SCALE)).exp()

    def forward(self, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        m = self.encode_motion(batch["motion"], batch["lengths"])
        t = self.encode_text(batch["tokens"], batch["mask"])
        loss = contrastive_loss(t.float(), m.float(), self.scale(), batch.get("groups"))
        with torch.no_grad():
            sims = t.float() @ m.float().T
            top1 = (sims.argmax(1) == torch.arange(len(t))).float().mean()
        return loss, {"loss": float(loss.detach()), "batch_top1": float(top1), "temperature": float(1.0 / self.scale().detach())}


def check_feature_list(features_list: Sequence, where: str = "features") -> list[np.ndarray]:
    if isinstance(features_list, np.ndarray) and features_list.ndim == 2:
        raise TypeError(f"{where}: expected a list of (T, {FEATURE_DIM}) arrays, got one array; wrap it in a list")
    out = []
    for i, f in enumerate(features_list):
        a = f.detach().cpu().numpy() if isinstance(f, torch.Tensor) else np.asarray(f)
        if a.ndim != 2 or a.shape[1] != FEATURE_DIM:
            raise ValueError(f"{where}[{i}]: expected shape (T, {FEATURE_DIM}), got {a.shape}")
        if len(a) < DOWNSAMPLE:
            raise ValueError(f"{where}[{i}]: {len(a)} frames; at least {DOWNSAMPLE} are needed")
        if not np.isfinite(a).all():
            raise ValueError(f"{where}[{i}]: contains NaN or infinite values")
        out.append(a.astype(np.float32, copy=False))
    return out


def pad_batch(arrays: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """Zero-padded (B, T, C) tensor and lengths (B,)."""
    lengths = torch.tensor([len(a) for a in arrays])
    out = torch.zeros(len(arrays), int(lengths.max()), arrays[0].shape[1])
    for b, a in enumerate(arrays):
        out[b, :len(a)] = torch.from_numpy(a)
    return out, lengths


def embed_motion_batches(encode, features: list[np.ndarray], batch_size: int) -> np.ndarray:
    """Run `encode(padded, lengths)` over batches of similar length; rows come back in input order."""
    order = np.argsort([len(f) for f in features], kind="stable")
    out: np.ndarray | None = None
    for s in range(0, len(order), batch_size):
        idx = order[s:s + batch_size]
        x, lengths = pad_batch([features[i] for i in idx])
        emb = encode(x, lengths).float().cpu().numpy()
        if out is None:
            out = np.empty((len(features), emb.shape[1]), dtype=np.float32)
        out[idx] = emb
    return out


class Evaluator:
    """A trained evaluator ready for embedding (always in eval mode, no gradients)."""

    def __init__(self, matcher: TextMotionMatcher, mean: np.ndarray, std: np.ndarray, text_encoder=None,
                 batch_size: int = 64):
        mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
        if mean.shape != (FEATURE_DIM,) or std.shape != (FEATURE_DIM,):
            raise ValueError(f"normalisation stats must be ({FEATURE_DIM},), got {mean.shape} and {std.shape}")
        self.matcher = matcher.eval()
        self.cfg = matcher.cfg
        self.mean, self.std = mean, std
        self._text_encoder = text_encoder
        self.batch_size = batch_size
        self.meta: dict[str, Any] = {}

    @property
    def dim(self) -> int:
        return self.cfg.motion.output_dim

    @property
    def text_encoder(self):
        if self._text_encoder is None:
            from ..models.text import load_text_encoder
            self._text_encoder = load_text_encoder(self.cfg.text_encoder)
        return self._text_encoder

    def normalize(self, features: np.ndarray) -> np.ndarray:
        """Raw (T, 263) -> normalised (T, 259) evaluator input."""
        k = FEATURE_DIM - CONTACT_CHANNELS
        return ((features[:, :k] - self.mean[:k]) / self.std[:k]).astype(np.float32)

    @torch.no_grad()
    def embed_motions(self, features_list: Sequence) -> np.ndarray:
        """Raw (T, 263) motions -> (N, D) unit-norm embeddings."""
        feats = [self.normalize(f) for f in check_feature_list(features_list)]
        if not feats:
            return np.zeros((0, self.dim), np.float32)
        self.matcher.eval()
        return embed_motion_batches(self.matcher.encode_motion, feats, self.batch_size)

    @torch.no_grad()
    def embed_text_features(self, tokens: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
        """The evaluator stays on the CPU; the features may come from a text encoder on a GPU."""
        self.matcher.eval()
        return self.matcher.encode_text(tokens.cpu(), mask.cpu()).float().numpy()

    @torch.no_grad()
    def embed_texts(self, captions: Sequence[str]) -> np.ndarray:
        """Captions -> (N, D) unit-norm embeddings."""
        captions = list(captions)
        if not captions:
            return np.zeros((0, self.dim), np.float32)
        out = []
        for s in range(0, len(captions), self.batch_size):
            f = self.text_encoder.encode(captions[s:s + self.batch_size])
            out.append(self.embed_text_features(f.tokens, f.mask))
        return np.concatenate(out)


def save_evaluator(path: str | Path, matcher: TextMotionMatcher, mean: np.ndarray, std: np.ndarray,
                   meta: dict[str, Any] | None = None) -> Path:
    return save_scorer(path, KIND, matcher, mean, std, meta)


def load_evaluator(path: str | Path, text_encoder=None) -> Evaluator:
    """An evaluator checkpoint directory -> Evaluator (the text encoder loads on first use unless given)."""
    matcher, mean, std, doc = load_scorer(path, KIND, EvaluatorConfig, TextMotionMatcher)
    if text_encoder is not None and getattr(text_encoder, "spec", None) is not None:
        got = text_encoder.spec().get("kind")
        if got != matcher.cfg.text_encoder.split(":")[0]:
            raise ValueError(f"{path}: trained with text encoder {matcher.cfg.text_encoder!r}, given a {got!r} encoder")
    ev = Evaluator(matcher, mean, std, text_encoder)
    ev.meta = doc.get("meta", {})
    return ev
