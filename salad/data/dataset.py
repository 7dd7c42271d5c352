"""Torch datasets over any HumanML3D-layout directory.

A directory holds `new_joint_vecs/<id>.npy` (T, D) features (D = 263 for HumanML3D and
builds made here, 251 for KIT-ML), `texts/<id>.txt` captions in the
`caption#tagged tokens#start#end` line format, `train.txt` / `val.txt` / `test.txt`
id lists and `Mean.npy` / `Std.npy`. Timestamped captions become their own sub-clip
samples, as in HumanML3D's loaders.
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from ..motion.representation import FPS, Normalizer


class DatasetError(ValueError):
    pass


@dataclass
class Caption:
    text: str
    tokens: str
    start: float
    end: float


def parse_caption_line(line: str, where: str = "") -> Caption:
    parts = line.rstrip("\n").split("#")
    if len(parts) < 4 or not parts[0].strip():
        raise DatasetError(f"{where}: bad caption line {line!r} (expected caption#tokens#start#end)")
    try:
        start = float(parts[-2]) if parts[-2].strip() else 0.0
        end = float(parts[-1]) if parts[-1].strip() else 0.0
    except ValueError:
        raise DatasetError(f"{where}: bad timestamps in caption line {line!r}") from None
    start = 0.0 if np.isnan(start) else start
    end = 0.0 if np.isnan(end) else end
    return Caption("#".join(parts[:-3]).strip(), parts[-3], start, end)


def read_captions(path: Path) -> list[Caption]:
    lines = [l for l in path.read_text(encoding="utf-8").splitlines() if l.strip()]
    return [parse_caption_line(l, str(path)) for l in lines]


def read_split(root: Path, split: str) -> list[str]:
    f = root / f"{split}.txt"
    if not f.is_file():
        raise DatasetError(f"{root}: no {split}.txt split file")
    return [l.strip() for l in f.read_text().splitlines() if l.strip()]


def load_normalizer(root: str | Path) -> Normalizer:
    root = Path(root)
    try:
        return Normalizer(np.load(root / "Mean.npy"), np.load(root / "Std.npy"))
    except FileNotFoundError as e:
        raise DatasetError(f"{root}: missing {Path(e.filename).name}") from None


@dataclass
class MotionItem:
    name: str
    features: np.ndarray          # (T, D) raw (not normalised)
    captions: list[str]


class MotionDataset(Dataset):
    """Whole motions (or timestamped sub-clips) with their captions.

    Items are dicts: `features` (T, D) normalised float32, `length` T, `caption` (one
    caption drawn at random), `name`. Motions shorter than `min_frames` are dropped;
    longer than `max_frames` are kept and cropped at random when drawn (or at the
    start when `random_crop` is False).
    """

    def __init__(self, root: str | Path, split: str = "train", min_frames: int = 16, max_frames: int = 196,
                 normalizer: Normalizer | None = None, random_crop: bool = True, limit: int | None = None,
                 require_captions: bool = True):
        """require_captions=False also keeps motions without a texts/ file (caption ""), for the
        VAE, which learns from motion alone (`salad data build --allow-uncaptioned`)."""
        self.root = Path(root)
        if not (self.root / "new_joint_vecs").is_dir():
            raise DatasetError(f"{self.root}: not a HumanML3D-layout directory (no new_joint_vecs/)")
        self.normalizer = normalizer or load_normalizer(self.root)
        self.min_frames, self.max_frames, self.random_crop = min_frames, max_frames, random_crop
        self.items: list[MotionItem] = []
        skipped = 0
        for name in read_split(self.root, split)[:limit]:
            f = self.root / "new_joint_vecs" / f"{name}.npy"
            t = self.root / "texts" / f"{name}.txt"
            if not f.is_file() or (require_captions and not t.is_file()):
                skipped += 1
                continue
            feats = np.load(f).astype(np.float32)
            if feats.ndim != 2 or feats.shape[1] != self.normalizer.dim:
                raise DatasetError(f"{f}: shape {feats.shape} does not match Mean.npy's {self.normalizer.dim} dims")
            whole, clips = [], {}
            for cap in (read_captions(t) if t.is_file() else []):
                if cap.start == 0.0 and cap.end == 0.0:
                    whole.append(cap.text)
                else:
                    clips.setdefault((cap.start, cap.end), []).append(cap.text)
            if not whole and not clips and not require_captions:
                whole = [""]                  # an uncaptioned motion, whole
            if whole and len(feats) >= min_frames:
                self.items.append(MotionItem(name, feats, whole))
            for (s, e), texts in clips.items():
                sub = feats[int(s * FPS):int(e * FPS)]
                if len(sub) >= min_frames:
                    self.items.append(MotionItem(f"{name}@{s:g}-{e:g}", sub, texts))
        self.skipped = skipped
        if not self.items:
            raise DatasetError(f"{self.root}: split {split!r} has no usable motions")
        self.dim = self.normalizer.dim

    def __len__(self) -> int:
        return len(self.items)

    def crop(self, feats: np.ndarray, rng: random.Random) -> np.ndarray:
        if len(feats) <= self.max_frames:
            return feats
        start = rng.randint(0, len(feats) - self.max_frames) if self.random_crop else 0
        return feats[start:start + self.max_frames]

    def get(self, i: int, rng: random.Random) -> dict:
        item = self.items[i]
        feats = self.crop(item.features, rng)
        return {"features": self.normalizer.normalize(feats).astype(np.float32), "length": len(feats),
                "caption": rng.choice(item.captions), "name": item.name}

    def __getitem__(self, i: int) -> dict:
        return self.get(i, random)


def collate_motions(items: list[dict], multiple: int = 4, pad_to: int | None = None) -> dict:
    """Pad a list of dataset items into a batch.

    Lengths are cut down to a multiple of `multiple` (the VAE halves time twice).
    Returns features (B, T, D), valid (B, T) bool, lengths (B,), captions, names.
    """
    lengths = [(it["length"] // multiple) * multiple for it in items]
    if min(lengths) <= 0:
        raise DatasetError(f"a motion is shorter than {multiple} frames")
    T = pad_to or max(lengths)
    D = items[0]["features"].shape[-1]
    feats = torch.zeros(len(items), T, D)
    valid = torch.zeros(len(items), T, dtype=torch.bool)
    for b, (it, n) in enumerate(zip(items, lengths)):
        n = min(n, T)
        feats[b, :n] = torch.from_numpy(it["features"][:n])
        valid[b, :n] = True
    return {"features": feats, "valid": valid, "lengths": torch.tensor([min(n, T) for n in lengths]),
            "captions": [it["caption"] for it in items], "names": [it["name"] for it in items]}


class WindowSampler:
    """Fixed-length training windows for the VAE, drawn uniformly over all frames, or motion by
    motion in proportion to item_weights.

    A window may run past a motion's end; the overhang is zero (the mean pose in
    normalised space) with activation 0, which is how the VAE learns to mark the end
    of a motion (MoLA). `overhang` bounds how much of a window may be padding.
    """

    def __init__(self, dataset: MotionDataset, window: int = 64, overhang: float = 0.5,
                 item_weights: np.ndarray | None = None):
        """item_weights: how often to draw each motion (default: in proportion to its length)."""
        self.ds, self.window, self.overhang = dataset, window, overhang
        if item_weights is None:
            item_weights = [len(it.features) for it in dataset.items]
        w = np.asarray(item_weights, dtype=np.float64)
        self.weights = w / w.sum()

    def batch(self, size: int, rng: np.random.Generator) -> dict:
        W = self.window
        idx = rng.choice(len(self.ds.items), size=size, p=self.weights)
        feats = np.zeros((size, W, self.ds.dim), dtype=np.float32)
        act = np.zeros((size, W), dtype=np.float32)
        for b, i in enumerate(idx):
            f = self.ds.items[i].features
            max_pad = int(W * self.overhang)
            start = int(rng.integers(0, max(1, len(f) - W + max_pad + 1)))
            chunk = f[start:start + W]
            feats[b, :len(chunk)] = self.ds.normalizer.normalize(chunk)
            act[b, :len(chunk)] = 1.0
        return {"features": torch.from_numpy(feats), "activation": torch.from_numpy(act)}


def read_clip(root: Path, name: str, max_frames: int) -> tuple[np.ndarray, str]:
    """(features cut to at most max_frames, the clip's first caption)."""
    f = np.load(root / "new_joint_vecs" / f"{name}.npy", allow_pickle=False)
    caps = read_captions(root / "texts" / f"{name}.txt")
    if not caps:
        raise ValueError(f"{root}/texts/{name}.txt: no captions")
    return f[:max_frames], caps[0].text
