"""Training the content/style/side motion classifier.

    salad train classifier --config configs/classifier.toml

Training draws motions with probability proportional to count(content, style)^-balance, so the rare
labels of the smaller recording set are seen often enough. The exported model is the one with the best
mean validation accuracy over the heads.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from ..files import atomic_write_text
from ..config import apply_overrides, load_toml, to_dict, validate
from ..data.dataset import MotionDataset, load_normalizer
from .configs import OptimConfig, RunConfig
from ..eval.classifiers import HEADS, KIND, Classifier, ClassifierConfig, MotionClassifier, load_classifier, save_classifier
from ..data.labels import MotionLabels, read_labels
from ..eval.networks import CONTACT_CHANNELS
from ..eval.sampling import fixed_crop, normalized_batch, random_crop
from ..eval.selection import best_score, log_validation


@dataclass
class ClassifierDataConfig:
    root: str = "data/bandai-hml"
    min_frames: int = 16
    max_frames: int = 196
    shorten_prob: float = 0.33
    balance: float = 0.5     # 0 = uniform over motions, 1 = uniform over (content, style) pairs


@dataclass
class ClassifierTrainConfig:
    data: ClassifierDataConfig = field(default_factory=ClassifierDataConfig)
    model: ClassifierConfig = field(default_factory=ClassifierConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(
        lr=1e-3, betas=(0.9, 0.99), weight_decay=1e-4, warmup_steps=100, milestones=(), batch_size=128,
        max_steps=600, grad_clip=1.0))
    run: RunConfig = field(default_factory=lambda: RunConfig(out_dir="runs/classifier", bf16=False,
                                                             checkpoint_every=100, log_every=25))


def label_indices(ds: MotionDataset, labels: dict[str, MotionLabels], classes: dict) -> dict[str, np.ndarray]:
    """{head: (N,) class index per dataset item}."""
    out = {h: np.empty(len(ds.items), dtype=np.int64) for h in classes}
    lookup = {h: {c: i for i, c in enumerate(names)} for h, names in classes.items()}
    for i, it in enumerate(ds.items):
        lab = labels.get(it.name)
        if lab is None:
            raise ValueError(f"{ds.root}/labels.json: no labels for motion {it.name!r}")
        for h in classes:
            value = getattr(lab, h)
            if value not in lookup[h]:
                raise ValueError(f"{ds.root}/labels.json: motion {it.name!r} has {h} {value!r}, not among the "
                                 f"classifier's classes")
            out[h][i] = lookup[h][value]
    return out


def accuracy_report(clf: Classifier, ds: MotionDataset, targets: dict[str, np.ndarray],
                    max_frames: int) -> dict[str, dict[str, Any]]:
    """Per head: accuracy, balanced accuracy (mean recall over the classes present), the count, and
    per class present its count and what the wrong predictions were ({class: {"n", "wrong": {class: count}}})."""
    probs = clf.probabilities([fixed_crop(it.features, max_frames) for it in ds.items])
    out = {}
    for h, p in probs.items():
        pred, y = p.argmax(1), targets[h]
        names, per_class = clf.classes[h], {}
        for c in np.unique(y):
            wrong = pred[(y == c) & (pred != c)]
            per_class[names[c]] = {"n": int((y == c).sum()),
                                   "wrong": {names[w]: int((wrong == w).sum()) for w in np.unique(wrong)}}
        recall = [1 - sum(c["wrong"].values()) / c["n"] for c in per_class.values()]
        out[h] = {"accuracy": float((pred == y).mean()), "balanced_accuracy": float(np.mean(recall)),
                  "n": int(len(y)), "classes": per_class}
    return out


class ClassifierTask:
    kind = KIND

    def __init__(self, cfg: ClassifierTrainConfig):
        validate(cfg)
        self.cfg = cfg
        d = cfg.data
        self.normalizer = load_normalizer(d.root)
        labels = read_labels(d.root)
        self.train = MotionDataset(d.root, "train", min_frames=d.min_frames, max_frames=10 ** 9,
                                   normalizer=self.normalizer)
        self.val = MotionDataset(d.root, "val", min_frames=d.min_frames, max_frames=10 ** 9,
                                 normalizer=self.normalizer)
        if not cfg.model.classes:
            # every label of the whole dataset, so val/test motions always have a class (even one that
            # training never shows)
            used = {h: {getattr(lab, h) for lab in labels.values()} for h in HEADS}
            cfg.model.classes = {h: [c for c in HEADS[h] if c in used[h]] for h in HEADS}
        classes = cfg.model.classes
        self.targets = label_indices(self.train, labels, classes)
        self.val_targets = label_indices(self.val, labels, classes)
        pair = [(labels[it.name].content, labels[it.name].style) for it in self.train.items]
        counts: dict[tuple, int] = {}
        for p in pair:
            counts[p] = counts.get(p, 0) + 1
        w = np.array([counts[p] ** -d.balance for p in pair])
        self.weights = w / w.sum()
        torch.manual_seed(cfg.run.seed)
        self.model = MotionClassifier(cfg.model)
        k = self.normalizer.dim - CONTACT_CHANNELS
        self.mean, self.std = self.normalizer.mean[:k], self.normalizer.std[:k]

    def batch(self, rng: np.random.Generator) -> dict:
        d = self.cfg.data
        idx = rng.choice(len(self.train.items), size=self.cfg.optim.batch_size, p=self.weights)
        crops = [random_crop(self.train.items[i].features, d.max_frames, rng, d.shorten_prob, d.min_frames)
                 for i in idx]
        motion, lengths = normalized_batch(crops, self.mean, self.std)
        out = {"motion": motion, "lengths": lengths}
        for h, t in self.targets.items():
            out[h] = torch.from_numpy(t[idx])
        return out

    def loss(self, model: nn.Module, batch: dict):
        return model(batch)

    def config_dict(self) -> dict:
        return to_dict(self.cfg)

    def validate(self, model: MotionClassifier) -> dict[str, Any]:
        was_training = model.training
        try:
            clf = Classifier(model, self.normalizer.mean, self.normalizer.std)
            report = accuracy_report(clf, self.val, self.val_targets, self.cfg.data.max_frames)
        finally:
            model.train(was_training)
        score = float(np.mean([r["accuracy"] for r in report.values()]))
        return {"score": score, **{h: r["accuracy"] for h, r in report.items()}}

    def export(self, model: nn.Module, path: Path, meta: dict[str, Any]) -> None:
        scores = self.validate(model)
        log_validation(path.parent, {"step": meta.get("step"), **{k: round(v, 4) for k, v in scores.items()}})
        if scores["score"] > best_score(path, KIND, self.cfg):
            save_classifier(path, model, self.normalizer.mean, self.normalizer.std,
                            {**meta, "val": scores, "train_config": self.config_dict()})


def train_classifier(args) -> int:
    """Train, select by validation accuracy, then report per-head accuracy on val and test."""
    from .loop import Trainer

    cfg = load_toml(ClassifierTrainConfig, args.config)
    apply_overrides(cfg, args)
    if cfg.run.threads:
        torch.set_num_threads(cfg.run.threads)
    t0 = time.time()
    task = ClassifierTask(cfg)
    out = Trainer(task, cfg.optim, cfg.run).fit()
    clf = load_classifier(out)
    summary: dict[str, Any] = {"model": str(out), "selected_step": clf.meta.get("step"),
                               "wall_time_s": round(time.time() - t0, 1),
                               **classifier_summary(clf, cfg.data.root, min_frames=cfg.data.min_frames,
                                                    max_frames=cfg.data.max_frames)}
    atomic_write_text(Path(cfg.run.out_dir) / "summary.json", json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    print(f"model written to {out}")
    for line in summary["warnings"]:
        print(f"warning: {line}")
    return 0


def classifier_summary(clf: Classifier, root: str | Path, splits=("train", "val", "test"), min_frames: int = 16,
                       max_frames: int = 196) -> dict[str, Any]:
    """accuracy_report per split, and warnings for the content classes the classifier calls something else
    in most of their training motions. Selection by validation accuracy cannot see those where the
    validation split lacks the class (an action captured once), yet every benchmark that asks the
    classifier for that action trusts them."""
    labels = read_labels(root)
    out: dict[str, Any] = {}
    for split in splits:
        ds = MotionDataset(root, split, min_frames=min_frames, max_frames=10 ** 9)
        out[split] = accuracy_report(clf, ds, label_indices(ds, labels, clf.classes), max_frames)
    out["warnings"] = misread_classes(out["train"]["content"]["classes"]) if "train" in out else []
    return out


def misread_classes(per_class: dict[str, dict]) -> list[str]:
    """One line per class (accuracy_report's "classes") that is called something else in more than half
    of its motions."""
    return [f"{name}: {sum(c['wrong'].values())} of its {c['n']} training motions are called "
            + ", ".join(f"{k} ({v})" for k, v in sorted(c["wrong"].items()))
            for name, c in sorted(per_class.items()) if 2 * sum(c["wrong"].values()) > c["n"]]


def write_classifier_report(results: dict, out: str | Path) -> Path:
    """results.json and report.md of `salad eval-classifier` (classifier_summary plus its inputs); the report's path."""
    splits = [s for s in ("train", "val", "test") if s in results]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    lines = [f"# Classifier `{results['classifier']}` on the real motions of `{results['data']}`", "",
             "| split | motions | content | style | side |", "|---|---|---|---|---|"]
    for s in splits:
        r = results[s]
        lines.append(f"| {s} | {r['content']['n']} | "
                     + " | ".join(f"{r[h]['accuracy']:.4f}" if h in r else "–" for h in ("content", "style", "side"))
                     + " |")
    lines += ["", "Content classes with wrong calls (true class: motions; wrong calls):", ""]
    for s in splits:
        for name, c in sorted(results[s]["content"]["classes"].items()):
            if c["wrong"]:
                lines.append(f"- {s}, {name}: {c['n']}; " + ", ".join(f"{k} {v}" for k, v in sorted(c["wrong"].items())))
    lines += ["", "Warnings: " + ("; ".join(results["warnings"]) or "none")]
    atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    return out / "report.md"
