"""Motion classifiers for the editing benchmark: content, style and side heads on one motion encoder.

The encoder is the evaluator's (movement convolutions + BiGRU over the 259 non-contact channels,
normalised with the dataset's Mean/Std). "side" is the body side or turn direction an action refers to
(none / left / right / both, see `salad.data.labels.side_of`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..config import ConfigError
from ..motion.representation import FEATURE_DIM
from .evaluator import check_feature_list, embed_motion_batches
from ..data.labels import CONTENTS, SIDES, STYLES
from .networks import CONTACT_CHANNELS, MotionEncoder, MotionEncoderConfig, load_scorer, save_scorer

KIND = "classifier"
# every label the caption templates know, per head (a dataset may use a subset)
HEADS: dict[str, tuple[str, ...]] = {"content": CONTENTS, "style": STYLES, "side": SIDES}


@dataclass
class ClassifierConfig:
    motion: MotionEncoderConfig = field(default_factory=lambda: MotionEncoderConfig(output_dim=256))
    dropout: float = 0.2
    label_smoothing: float = 0.05
    # head -> class names; empty = every label that occurs in the training data's labels.json
    classes: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.classes, dict):
            raise ConfigError("classes must map head names to class lists")
        for head, names in self.classes.items():
            if head not in HEADS:
                raise ConfigError(f"classes.{head}: unknown head; known heads: {sorted(HEADS)}")
            if not isinstance(names, (list, tuple)) or not names or len(set(names)) != len(names):
                raise ConfigError(f"classes.{head}: need a non-empty list of distinct class names")
        if self.motion.input_dim != FEATURE_DIM - CONTACT_CHANNELS:
            raise ConfigError(f"motion.input_dim must be {FEATURE_DIM - CONTACT_CHANNELS} (263 minus foot contacts)")


class MotionClassifier(nn.Module):
    """Normalised (B, T, 259) motions -> logits per head."""

    def __init__(self, cfg: ClassifierConfig):
        super().__init__()
        if not cfg.classes:
            raise ValueError("the classifier config lists no classes")
        self.cfg = cfg
        self.encoder = MotionEncoder(cfg.motion)
        self.drop = nn.Dropout(cfg.dropout)
        self.heads = nn.ModuleDict({h: nn.Linear(cfg.motion.output_dim, len(c)) for h, c in cfg.classes.items()})

    def logits(self, motion: torch.Tensor, lengths: torch.Tensor) -> dict[str, torch.Tensor]:
        z = self.drop(F.leaky_relu(self.encoder(motion, lengths), 0.2))
        return {h: head(z) for h, head in self.heads.items()}

    def forward(self, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        out = self.logits(batch["motion"], batch["lengths"])
        losses, logs = [], {}
        for h, logit in out.items():
            target = batch[h]
            losses.append(F.cross_entropy(logit, target, label_smoothing=self.cfg.label_smoothing))
            logs[f"acc_{h}"] = float((logit.argmax(1) == target).float().mean())
        loss = torch.stack(losses).mean()
        logs["loss"] = float(loss.detach())
        return loss, logs


class Classifier:
    """A trained classifier ready for prediction on raw (T, 263) features."""

    def __init__(self, model: MotionClassifier, mean: np.ndarray, std: np.ndarray, batch_size: int = 64):
        mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
        if mean.shape != (FEATURE_DIM,) or std.shape != (FEATURE_DIM,):
            raise ValueError(f"normalisation stats must be ({FEATURE_DIM},), got {mean.shape} and {std.shape}")
        self.model = model.eval()
        self.mean, self.std = mean, std
        self.batch_size = batch_size
        self.classes = {h: list(c) for h, c in model.cfg.classes.items()}
        self.meta: dict[str, Any] = {}

    def normalize(self, features: np.ndarray) -> np.ndarray:
        k = FEATURE_DIM - CONTACT_CHANNELS
        return ((features[:, :k] - self.mean[:k]) / self.std[:k]).astype(np.float32)

    @torch.no_grad()
    def probabilities(self, features_list: Sequence) -> dict[str, np.ndarray]:
        """{head: (N, classes) softmax probabilities}."""
        feats = [self.normalize(f) for f in check_feature_list(features_list)]
        heads = list(self.classes)
        if not feats:
            return {h: np.zeros((0, len(self.classes[h])), np.float32) for h in heads}
        self.model.eval()
        widths = np.cumsum([0] + [len(self.classes[h]) for h in heads])

        def encode(x, lengths):
            logits = self.model.logits(x, lengths)
            return torch.cat([torch.softmax(logits[h], 1) for h in heads], 1)

        probs = embed_motion_batches(encode, feats, self.batch_size)
        return {h: probs[:, widths[i]:widths[i + 1]] for i, h in enumerate(heads)}

    def predict(self, features_list: Sequence) -> dict[str, Any]:
        """{head: predicted class names, f"{head}_probs": (N, classes) probabilities}; class order in
        `self.classes`."""
        probs = self.probabilities(features_list)
        out: dict[str, Any] = {}
        for h, p in probs.items():
            out[h] = [self.classes[h][i] for i in p.argmax(1)]
            out[f"{h}_probs"] = p
        return out


def save_classifier(path: str | Path, model: MotionClassifier, mean: np.ndarray, std: np.ndarray,
                    meta: dict[str, Any] | None = None) -> Path:
    return save_scorer(path, KIND, model, mean, std, meta)


def load_classifier(path: str | Path) -> Classifier:
    model, mean, std, doc = load_scorer(path, KIND, ClassifierConfig, MotionClassifier)
    clf = Classifier(model, mean, std)
    clf.meta = doc.get("meta", {})
    return clf
