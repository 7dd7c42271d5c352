"""salad: skeleton-aware latent diffusion for text-driven motion generation and editing."""
from __future__ import annotations

from .editing.spec import EditSpec

__version__ = "0.1.0"


def load_pipeline(*args, **kwargs):
    """Load a model directory (default: the embedded model) -> Pipeline. See salad.pipeline."""
    from .pipeline import load_pipeline as _load
    return _load(*args, **kwargs)


__all__ = ["EditSpec", "load_pipeline", "__version__"]
