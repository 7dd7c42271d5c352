"""How long-running work reports how far it has got."""
from __future__ import annotations

from typing import Callable

# progress(done, total): both in the same unit (sampling steps, frames); called after each unit.
Progress = Callable[[int, int], None]
