"""The process settings the command line and the studio start with: offline, no telemetry. Importing the library
sets none of them (an API user's process keeps its own); the entry points call use_offline_defaults() first."""
from __future__ import annotations

import os

OFFLINE_DEFAULTS = {"HF_HUB_OFFLINE": "1", "HF_HUB_DISABLE_TELEMETRY": "1", "TRANSFORMERS_OFFLINE": "1",
                    "GRADIO_ANALYTICS_ENABLED": "False"}


def use_offline_defaults() -> None:
    """Never reach for a model hub or send analytics; a variable the caller set wins."""
    for key, value in OFFLINE_DEFAULTS.items():
        os.environ.setdefault(key, value)
