"""Text-to-motion metrics on embeddings (Guo et al., CVPR 2022), vectorised with NumPy.

All distances are Euclidean in the evaluator's embedding space. Functions take
(N, D) arrays; random choices take a NumPy Generator so results are reproducible.
"""
from __future__ import annotations

import numpy as np
from scipy import linalg

__all__ = [
    "gaussian_stats", "frechet_distance", "fid", "diversity", "pairwise_distances", "r_precision_counts",
    "r_precision", "matching_distance", "multimodality", "mean_ci",
]


def _as_2d(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"{name}: expected an (N, D) array, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    return a


def gaussian_stats(embeddings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and unbiased covariance (D, D) of (N, D) embeddings."""
    e = _as_2d(embeddings, "embeddings")
    if len(e) < 2:
        raise ValueError(f"embeddings: need at least 2 rows for a covariance, got {len(e)}")
    return e.mean(axis=0), np.cov(e, rowvar=False)


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray,
                     eps: float = 1e-6) -> float:
    """||mu1 - mu2||^2 + Tr(S1 + S2 - 2 (S1 S2)^1/2) between two Gaussians."""
    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    s1, s2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    if mu1.shape != mu2.shape or s1.shape != s2.shape or s1.shape != (mu1.size, mu1.size):
        raise ValueError(f"mismatched Gaussian shapes: mu {mu1.shape}/{mu2.shape}, sigma {s1.shape}/{s2.shape}")
    diff = mu1 - mu2
    covmean = linalg.sqrtm(s1 @ s2)
    if not np.isfinite(covmean).all():
        # singular product (fewer samples than dimensions): nudge both diagonals, as is customary
        offset = np.eye(s1.shape[0]) * eps
        covmean = linalg.sqrtm((s1 + offset) @ (s2 + offset))
    if np.iscomplexobj(covmean):
        # round-off gives tiny imaginary parts; a large one means the result is not trustworthy
        imag = np.abs(covmean.imag).max()
        scale = max(1.0, np.abs(covmean.real).max())
        if imag > 1e-3 * scale:
            raise ValueError(f"matrix square root has a large imaginary component ({imag:.3g})")
        covmean = covmean.real
    value = float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * np.trace(covmean))
    # the trace term can round a hair below zero for identical inputs
    return max(value, 0.0)


def fid(embeddings_a: np.ndarray, embeddings_b: np.ndarray) -> float:
    """Fréchet distance between Gaussian fits of two embedding sets."""
    return frechet_distance(*gaussian_stats(embeddings_a), *gaussian_stats(embeddings_b))


def diversity(embeddings: np.ndarray, pairs: int = 300, rng: np.random.Generator | None = None) -> float:
    """Mean distance between `pairs` random pairs (two draws without replacement, paired up)."""
    e = _as_2d(embeddings, "embeddings")
    if len(e) < 2:
        raise ValueError(f"diversity needs at least 2 embeddings, got {len(e)}")
    rng = rng or np.random.default_rng(0)
    n = min(pairs, len(e))
    first = rng.choice(len(e), n, replace=False)
    second = rng.choice(len(e), n, replace=False)
    return float(np.linalg.norm(e[first] - e[second], axis=1).mean())


def pairwise_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) Euclidean distances, via the expanded square with clamping of round-off."""
    a = _as_2d(a, "a")
    b = _as_2d(b, "b")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"embedding widths differ: {a.shape[1]} vs {b.shape[1]}")
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(sq, 0.0))


def r_precision_counts(text_emb: np.ndarray, motion_emb: np.ndarray, top_k: int = 3) -> np.ndarray:
    """Per text, whether its own motion (same row) is among the k nearest motions of the pool, for k = 1..top_k.

    Returns (N, top_k) booleans; a pool is the whole of the given rows (32 in the protocol).
    """
    d = pairwise_distances(text_emb, motion_emb)
    if d.shape[0] != d.shape[1]:
        raise ValueError(f"need as many texts as motions, got {d.shape[0]} and {d.shape[1]}")
    own = np.diag(d)[:, None]
    # rank = number of other motions at most as far as the true one: a tie is not a win, so a collapsed
    # evaluator (all embeddings equal) scores 0 rather than 1
    rank = (d <= own).sum(axis=1) - 1
    return rank[:, None] < np.arange(1, top_k + 1)[None, :]


def r_precision(text_emb: np.ndarray, motion_emb: np.ndarray, pool: int = 32, top_k: int = 3,
                drop_last: bool = True) -> np.ndarray:
    """R-precision top-1..top_k over consecutive pools of `pool` rows (the rows' order decides the pools)."""
    n = len(text_emb)
    if n != len(motion_emb):
        raise ValueError(f"need as many texts as motions, got {n} and {len(motion_emb)}")
    stops = list(range(0, n - pool + 1, pool)) if drop_last else list(range(0, n, pool))
    if not stops:
        raise ValueError(f"fewer rows ({n}) than one pool of {pool}")
    hits = [r_precision_counts(text_emb[s:s + pool], motion_emb[s:s + pool], top_k) for s in stops]
    return np.concatenate(hits).mean(axis=0)


def matching_distance(text_emb: np.ndarray, motion_emb: np.ndarray) -> float:
    """MM-Dist: mean distance between each text and its own motion."""
    t, m = _as_2d(text_emb, "text_emb"), _as_2d(motion_emb, "motion_emb")
    if t.shape != m.shape:
        raise ValueError(f"text and motion embeddings differ in shape: {t.shape} vs {m.shape}")
    return float(np.linalg.norm(t - m, axis=1).mean())


def multimodality(embeddings: np.ndarray, pairs: int = 10, rng: np.random.Generator | None = None) -> float:
    """Mean distance of `pairs` random pairs of generations of the same prompt, over prompts.

    `embeddings` is (prompts, generations per prompt, D).
    """
    e = np.asarray(embeddings, dtype=np.float64)
    if e.ndim != 3 or e.shape[1] < 2:
        raise ValueError(f"multimodality expects (prompts, repeats >= 2, D), got shape {e.shape}")
    if not np.isfinite(e).all():
        raise ValueError("multimodality: embeddings contain NaN or infinite values")
    rng = rng or np.random.default_rng(0)
    n = min(pairs, e.shape[1])
    first = rng.choice(e.shape[1], n, replace=False)
    second = rng.choice(e.shape[1], n, replace=False)
    return float(np.linalg.norm(e[:, first] - e[:, second], axis=-1).mean())


def mean_ci(values) -> tuple[float, float]:
    """Mean and 95% confidence half-width 1.96 * std / sqrt(N) (population std, as in the protocol)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        raise ValueError("mean_ci of no values")
    return float(v.mean()), float(1.96 * v.std() / np.sqrt(v.size))
