"""Cropping motions for evaluator/classifier training and for the evaluation protocol."""
from __future__ import annotations

import numpy as np

UNIT = 4  # lengths are multiples of the motion encoder's downsampling


def protocol_length(n_frames: int, max_frames: int) -> int:
    """Length used by the protocol: at most `max_frames`, cut down to a multiple of 4."""
    return (min(n_frames, max_frames) // UNIT) * UNIT


def random_crop(features: np.ndarray, max_frames: int, rng: np.random.Generator,
                shorten_prob: float = 0.0, min_frames: int = UNIT) -> np.ndarray:
    """A random window of protocol length; with probability `shorten_prob` one unit shorter (Guo et al.'s
    training augmentation), never below `min_frames`."""
    n = protocol_length(len(features), max_frames)
    if n < UNIT:
        raise ValueError(f"a motion of {len(features)} frames is shorter than {UNIT}")
    if shorten_prob > 0 and n - UNIT >= max(min_frames, UNIT) and rng.random() < shorten_prob:
        n -= UNIT
    start = int(rng.integers(0, len(features) - n + 1))
    return features[start:start + n]


def fixed_crop(features: np.ndarray, max_frames: int) -> np.ndarray:
    """The first protocol-length frames (deterministic reference crop)."""
    n = protocol_length(len(features), max_frames)
    if n < UNIT:
        raise ValueError(f"a motion of {len(features)} frames is shorter than {UNIT}")
    return features[:n]


def normalized_batch(crops: list[np.ndarray], mean: np.ndarray, std: np.ndarray):
    """Raw crops (T_i, >= C) -> zero-padded normalised (B, T, C) tensor of their first C = len(mean)
    channels, and lengths (B,)."""
    import torch

    k = len(mean)
    lengths = torch.tensor([len(c) for c in crops])
    out = torch.zeros(len(crops), int(lengths.max()), k)
    for b, c in enumerate(crops):
        out[b, :len(c)] = torch.from_numpy(((c[:, :k] - mean) / std).astype(np.float32))
    return out, lengths
