"""salad: skeleton-aware latent diffusion for text-driven motion generation and editing."""
from __future__ import annotations

import os

# torch's OpenMP runtime on Linux (libgomp) lets a waiting thread spin 300,000 times before it sleeps. Beside another
# busy process on two cores the spinning threads take the cores from the working ones: the student's generate and the
# feet refinement took three times as long beside a training run (30-36 s against 9.5-11 s for the same nine motions),
# the studio's edits twice as long. On an idle machine a short spin cost the studio's edits about a tenth and nothing
# measurable elsewhere, sampling or training (report assets/reports/studio-latency-77). libgomp reads it once, when
# torch loads, so it is set before anything here imports torch; a value the caller set wins.
os.environ.setdefault("GOMP_SPINCOUNT", "1000")

from .editing.spec import EditSpec  # noqa: E402

__version__ = "0.1.0"


def load_pipeline(*args, **kwargs):
    """Load a model directory (default: the embedded model) -> Pipeline. See salad.pipeline."""
    from .pipeline import load_pipeline as _load
    return _load(*args, **kwargs)


__all__ = ["EditSpec", "load_pipeline", "__version__"]
