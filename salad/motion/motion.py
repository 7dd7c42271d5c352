"""The Motion value returned by every generator, and how it is saved."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .bvh_export import DEFAULT_UNITS as DEFAULT_BVH_UNITS
from .representation import FPS
from ..files import atomic_write, check_writable_dir

OUTPUT_TYPES = (".npy", ".npz", ".bvh", ".mp4", ".gif", ".png")


def check_output_paths(outputs) -> list[Path]:
    """Output files Motion.save can write, checked before any work is done."""
    paths = [Path(o) for o in outputs]
    for p in paths:
        if p.suffix.lower() not in OUTPUT_TYPES:
            raise ValueError(f"{p}: unsupported output type {p.suffix or '(none)'!r}; use {', '.join(OUTPUT_TYPES)}")
        if p.is_dir():
            raise ValueError(f"{p}: is a directory; give a file name")
        check_writable_dir(p.parent)
    return paths


@dataclass
class Motion:
    """A motion: joints (T, 22, 3) in metres, Y-up, and its 263-d features (T, 263), at `fps`."""

    joints: np.ndarray
    features: np.ndarray
    fps: int = FPS
    text: str = ""
    seed: int | None = None
    attention: Any = None            # AttentionMaps when generated with return_attention=True
    info: dict = field(default_factory=dict)
    # how the model took the prompt: an action or words it was not trained on, another language
    # (salad.models.vocabulary); empty when all is well
    warnings: list[str] = field(default_factory=list)
    # the planted-feet refinement still to come (Pipeline.generate / edit / control with
    # foot_refine=False): calling it returns the refined motion (Pipeline.refine_feet); in memory only
    pending_refinement: Callable[[], "Motion"] | None = field(default=None, repr=False, compare=False)

    @property
    def frames(self) -> int:
        return int(self.joints.shape[0])

    @property
    def seconds(self) -> float:
        return self.frames / self.fps

    def save(self, path: str | Path, bvh_units: str = DEFAULT_BVH_UNITS) -> Path:
        """Write by extension: .npy (joints), .npz (joints + features), .bvh (in bvh_units:
        "cm" or "m"), .mp4, .gif, or .png (six evenly spaced frames side by side, for documents)."""
        path = Path(path)
        ext = path.suffix.lower()
        if ext == ".npy":
            _atomic_np(path, lambda f: np.save(f, self.joints.astype(np.float32)))
        elif ext == ".npz":
            _atomic_np(path, lambda f: np.savez(f, joints=self.joints.astype(np.float32),
                                                features=self.features.astype(np.float32), fps=self.fps))
        elif ext == ".bvh":
            from .bvh import save_bvh
            save_bvh(path, self.joints, fps=self.fps, units=bvh_units)
        elif ext == ".mp4":
            from ..render import render_video
            render_video(self.joints, path, fps=self.fps, title=self.text or None)
        elif ext == ".gif":
            from ..render import save_gif
            save_gif(self.joints, path, fps=self.fps, title=self.text or None)
        elif ext == ".png":
            from ..render import save_frame_strip
            save_frame_strip(self.joints, path, fps=self.fps, title=self.text or None)
        else:
            check_output_paths([path])
        return path


def _atomic_np(path: Path, write) -> None:
    atomic_write(path, write)
