"""Training the text-motion matching evaluator (`salad train evaluator --config configs/evaluator.toml`).

The frozen text encoder runs once over every distinct training/validation caption before training starts;
batches then only gather those token features. The exported model is the one with the best validation
R-precision (mean of top-1/2/3) among the periodic checkpoints.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn as nn

from ..files import atomic_write_text
from ..config import apply_overrides, load_toml, to_dict, validate
from ..data.dataset import MotionDataset, load_normalizer
from ..models.text_bank import TextBank
from .configs import OptimConfig, RunConfig
from ..eval.evaluator import KIND, Evaluator, EvaluatorConfig, TextMotionMatcher, load_evaluator, save_evaluator
from ..data.labels import read_labels
from ..eval.metrics import r_precision
from ..eval.networks import CONTACT_CHANNELS
from ..eval.sampling import fixed_crop, normalized_batch, random_crop
from ..eval.selection import best_score, log_validation


@dataclass
class EvalDataConfig:
    root: str = "data/bandai-hml"
    min_frames: int = 16
    max_frames: int = 196
    shorten_prob: float = 0.33      # Guo et al. drop one 4-frame unit in a third of the crops
    group_by_labels: bool = True    # same content/style/side = positive pair (needs labels.json)


@dataclass
class EvaluatorTrainConfig:
    data: EvalDataConfig = field(default_factory=EvalDataConfig)
    model: EvaluatorConfig = field(default_factory=EvaluatorConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(
        lr=1e-3, betas=(0.9, 0.99), weight_decay=1e-4, warmup_steps=100, milestones=(), batch_size=128,
        max_steps=1500, grad_clip=1.0))
    run: RunConfig = field(default_factory=lambda: RunConfig(out_dir="runs/evaluator", bf16=False,
                                                             checkpoint_every=100, log_every=25))
    val_pool: int = 32
    val_repeats: int = 10


def retrieval_precision(evaluator: Evaluator, dataset: MotionDataset, embed_captions: Callable[[list[str]], np.ndarray],
                        max_frames: int, pool: int = 32, repeats: int = 10, seed: int = 0) -> dict[str, float]:
    """R-precision top-1/2/3 of real motions (first `max_frames` frames) against their own captions, each
    repeat drawing a new order (hence new pools) and a new caption per motion."""
    items = dataset.items
    motion = evaluator.embed_motions([fixed_crop(it.features, max_frames) for it in items])
    caps = [c for it in items for c in it.captions]
    text = embed_captions(caps)
    first = np.cumsum([0] + [len(it.captions) for it in items[:-1]])
    rng = np.random.default_rng(seed)
    scores = []
    for _ in range(repeats):
        order = rng.permutation(len(items))
        pick = np.array([first[i] + rng.integers(len(items[i].captions)) for i in order])
        scores.append(r_precision(text[pick], motion[order], pool=pool))
    s = np.mean(scores, axis=0)
    return {"top1": float(s[0]), "top2": float(s[1]), "top3": float(s[2])}


class EvaluatorTask:
    """What the training loop needs: batches, the loss and the export with validation-based selection."""

    kind = KIND

    def __init__(self, cfg: EvaluatorTrainConfig, text_encoder=None, progress: bool = True):
        validate(cfg)
        self.cfg = cfg
        d = cfg.data
        self.normalizer = load_normalizer(d.root)
        self.train = MotionDataset(d.root, "train", min_frames=d.min_frames, max_frames=10 ** 9,
                                   normalizer=self.normalizer)
        self.val = MotionDataset(d.root, "val", min_frames=d.min_frames, max_frames=10 ** 9,
                                 normalizer=self.normalizer)
        if len(self.val) < cfg.val_pool:
            raise ValueError(f"{d.root}: the val split has {len(self.val)} usable motions, fewer than one "
                             f"R-precision pool (val_pool = {cfg.val_pool})")
        self.groups = self._groups(self.train) if d.group_by_labels else None
        if text_encoder is None:
            from ..models.text import load_text_encoder
            text_encoder = load_text_encoder(cfg.model.text_encoder)
        self.text_encoder = text_encoder
        captions = [c for ds in (self.train, self.val) for it in ds.items for c in it.captions]
        self.bank = TextBank(text_encoder, captions, progress=progress)
        self.caption_ids = [[self.bank.index[c] for c in it.captions] for it in self.train.items]
        torch.manual_seed(cfg.run.seed)
        self.model = TextMotionMatcher(cfg.model)
        k = self.normalizer.dim - CONTACT_CHANNELS
        self.mean, self.std = self.normalizer.mean[:k], self.normalizer.std[:k]
        self.history: list[dict] = []

    def _groups(self, ds: MotionDataset) -> np.ndarray:
        labels = read_labels(ds.root)
        keys = {}
        out = np.empty(len(ds.items), dtype=np.int64)
        for i, it in enumerate(ds.items):
            lab = labels.get(it.name)
            if lab is None:
                raise ValueError(f"{ds.root}/labels.json: no labels for motion {it.name!r}")
            out[i] = keys.setdefault((lab.content, lab.style, lab.side), len(keys))
        return out

    def batch(self, rng: np.random.Generator) -> dict:
        d = self.cfg.data
        idx = rng.integers(0, len(self.train.items), self.cfg.optim.batch_size)
        crops = [random_crop(self.train.items[i].features, d.max_frames, rng, d.shorten_prob, d.min_frames)
                 for i in idx]
        motion, lengths = normalized_batch(crops, self.mean, self.std)
        caps = [self.caption_ids[i][int(rng.integers(len(self.caption_ids[i])))] for i in idx]
        tokens, mask = self.bank.gather(caps)
        out = {"motion": motion, "lengths": lengths, "tokens": tokens, "mask": mask}
        if self.groups is not None:
            out["groups"] = torch.from_numpy(self.groups[idx])
        else:
            out["groups"] = torch.as_tensor(caps)  # identical captions are positives
        return out

    def loss(self, model: nn.Module, batch: dict):
        return model(batch)

    def config_dict(self) -> dict:
        return to_dict(self.cfg)

    def embed_bank(self, evaluator: Evaluator) -> Callable[[list[str]], np.ndarray]:
        def embed(captions: list[str]) -> np.ndarray:
            out = []
            for s in range(0, len(captions), 256):
                tokens, mask = self.bank.gather([self.bank.index[c] for c in captions[s:s + 256]])
                out.append(evaluator.embed_text_features(tokens, mask))
            return np.concatenate(out)
        return embed

    def validate(self, matcher: TextMotionMatcher) -> dict[str, float]:
        was_training = matcher.training
        ev = Evaluator(matcher, self.normalizer.mean, self.normalizer.std, self.text_encoder)
        try:
            scores = retrieval_precision(ev, self.val, self.embed_bank(ev), self.cfg.data.max_frames,
                                         self.cfg.val_pool, self.cfg.val_repeats, seed=0)
        finally:
            matcher.train(was_training)
        scores["score"] = (scores["top1"] + scores["top2"] + scores["top3"]) / 3
        return scores

    def export(self, model: nn.Module, path: Path, meta: dict[str, Any]) -> None:
        scores = self.validate(model)
        record = {"step": meta.get("step"), **{k: round(v, 4) for k, v in scores.items()}}
        self.history.append(record)
        log_validation(path.parent, record)
        if scores["score"] > best_score(path, KIND, self.cfg):
            save_evaluator(path, model, self.normalizer.mean, self.normalizer.std,
                           {**meta, "val": scores, "train_config": self.config_dict()})


def load_config(args) -> EvaluatorTrainConfig:
    cfg = load_toml(EvaluatorTrainConfig, args.config)
    apply_overrides(cfg, args)
    return cfg


def train_evaluator(args, text_encoder=None) -> int:
    """Train, select by validation R-precision, then score the selected model on val and test."""
    from .loop import Trainer

    cfg = load_config(args)
    if cfg.run.threads:
        torch.set_num_threads(cfg.run.threads)  # before the text features are computed, not only in the loop
    t0 = time.time()
    task = EvaluatorTask(cfg, text_encoder)
    t_text = time.time() - t0
    print(f"{len(task.train)} train / {len(task.val)} val motions, {len(task.bank.captions)} captions encoded "
          f"in {t_text:.0f} s", flush=True)
    out = Trainer(task, cfg.optim, cfg.run).fit()
    t_train = time.time() - t0
    ev = load_evaluator(out, task.text_encoder)
    summary: dict[str, Any] = {"model": str(out), "selected_step": ev.meta.get("step"),
                               "text_features_s": round(t_text, 1), "wall_time_s": round(t_train, 1)}
    for split in ("val", "test"):
        ds = MotionDataset(cfg.data.root, split, min_frames=cfg.data.min_frames, max_frames=10 ** 9,
                           normalizer=task.normalizer)
        summary[split] = retrieval_precision(ev, ds, ev.embed_texts, cfg.data.max_frames, cfg.val_pool,
                                             repeats=20, seed=1)
    atomic_write_text(Path(cfg.run.out_dir) / "summary.json", json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    print(f"model written to {out}")
    return 0
