"""How long-running work reports how far it has got."""
from __future__ import annotations

from typing import Callable

# progress(done, total): both in the same unit (sampling steps, frames); called after each unit.
Progress = Callable[[int, int], None]


def continued(progress: Progress | None, spent: int) -> Progress | None:
    """progress for work that follows `spent` units already reported (a sampling run again): the count
    goes on (spent + i of spent + n) rather than starting again from zero."""
    return None if progress is None else lambda i, n: progress(spent + i, spent + n)
