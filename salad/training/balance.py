"""How often each training motion is drawn, by its content class (data.balance)."""
from __future__ import annotations

import numpy as np

from ..config import ConfigError
from ..data.dataset import MotionDataset
from ..data.labels import content_of
from .configs import check_balance


def dataset_content(dataset: MotionDataset) -> list[str]:
    """Each training motion's content class, from the dataset's labels.json."""
    try:
        return content_of(dataset.root, [it.name for it in dataset.items])
    except (FileNotFoundError, ValueError) as e:
        raise ConfigError(f"data.balance draws by content class, which needs every training motion labelled "
                          f"({e}); set data.balance = 1 to draw motions as recorded") from None


def class_weights(content: list[str] | None, balance: float) -> np.ndarray | None:
    """Probability of drawing each item so that a content class with n clips is drawn in
    proportion to n**balance (None: uniform, balance = 1)."""
    if check_balance(balance) == 1.0:
        return None
    if content is None:
        raise ConfigError(f"data.balance = {balance} draws by content class, and this data has no content "
                          "labels; set data.balance = 1 to draw motions as recorded")
    names, cls, counts = np.unique(content, return_inverse=True, return_counts=True)
    w = counts[cls].astype(np.float64) ** (balance - 1.0)
    return w / w.sum()


def window_weights(dataset: MotionDataset, balance: float) -> np.ndarray | None:
    """How often the VAE draws a window from each motion: a content class with F frames in all
    in proportion to F**balance, and within it each motion by its length (None: every frame alike,
    balance = 1)."""
    if check_balance(balance) == 1.0:
        return None
    content = dataset_content(dataset)
    lengths = np.array([len(it.features) for it in dataset.items], dtype=np.float64)
    names, cls = np.unique(content, return_inverse=True)
    frames = np.bincount(cls, weights=lengths)
    w = lengths / frames[cls] * frames[cls] ** balance
    return w / w.sum()
