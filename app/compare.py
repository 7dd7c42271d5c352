"""How two motions differ, in numbers a summary line can carry: per body part pose change,
root path change and length change."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from salad.motion import skeleton as sk

PART_NAMES = tuple(n.replace("_", " ") for n in sk.BODY_PARTS.names)


@dataclass(frozen=True)
class Difference:
    part_change_m: dict[str, float]   # mean pelvis-relative distance of each part's joints (not the root's)
    root_change_m: float              # mean horizontal distance between the two pelvis paths
    frames: tuple[int, int]

    @property
    def most_changed(self) -> tuple[str, float]:
        name = max(self.part_change_m, key=self.part_change_m.get)
        return name, self.part_change_m[name]


def motion_difference(a: np.ndarray, b: np.ndarray) -> Difference:
    """Compare joints a and b (T, 22, 3) over their shared frames. Poses are compared relative
    to the pelvis so that a changed path does not count as a changed pose."""
    n = min(len(a), len(b))
    ja, jb = np.asarray(a[:n], dtype=np.float64), np.asarray(b[:n], dtype=np.float64)
    ra, rb = ja - ja[:, :1], jb - jb[:, :1]
    dist = np.linalg.norm(ra - rb, axis=-1).mean(axis=0)                    # (22,)
    root_part = sk.PART_OF_JOINT[0]      # the pelvis alone: its change is the path change below
    parts = {PART_NAMES[p]: float(dist[sk.PART_OF_JOINT == p].mean())
             for p in range(sk.BODY_PARTS.size) if p != root_part}
    root = float(np.linalg.norm((ja[:, 0] - jb[:, 0])[:, [0, 2]], axis=-1).mean())
    return Difference(parts, root, (len(a), len(b)))
