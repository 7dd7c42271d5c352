"""What an attention edit is asked to do (EditSpec) and what it gives back (EditResult)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..motion.motion import Motion


@dataclass
class EditResult:
    source: Motion
    edited: Motion
    source_attention: object = None
    edited_attention: object = None
    params: dict = field(default_factory=dict)
