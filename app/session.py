"""What one session holds between requests: its latest motions and what was rendered from them."""
from __future__ import annotations

import shutil
import threading
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .validation import GenerateRequest

KEEP_RESULTS = 2        # the previous motion's files stay while its downloads may still be fetched
CACHE_ENTRIES = 48      # renders kept per motion (word x aggregation combinations)


@dataclass
class Result:
    """One generated motion, where its files live, and a cache of views rendered from it."""

    request: GenerateRequest
    motion: Any                         # salad Motion, with .attention
    folder: Path
    files: dict[str, Path] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])

    def __post_init__(self):
        self._cache: OrderedDict[tuple, Any] = OrderedDict()
        self._lock = threading.Lock()

    def cached(self, key: tuple, make: Callable[[], Any]) -> Any:
        """The value stored under `key`, made on first use. A cached file that has since
        disappeared (pruned) is made again. Two requests for the same new key may both
        make it; the results are equal, so the last one simply wins."""
        with self._lock:
            if key in self._cache:
                value = self._cache[key]
                if not _missing_file(value):
                    self._cache.move_to_end(key)
                    return value
        value = make()
        with self._lock:
            self._cache[key] = value
            while len(self._cache) > CACHE_ENTRIES:
                self._cache.popitem(last=False)
        return value


def _missing_file(value) -> bool:
    items = value if isinstance(value, (list, tuple)) else [value]
    return any(isinstance(v, Path) and not v.exists() for v in items)


class Session:
    """A browser tab or API client: its folder and its most recent results."""

    def __init__(self, key: str, folder: Path):
        self.key, self.folder = key, folder
        self._results: list[Result] = []
        self._lock = threading.Lock()

    @property
    def current(self) -> Result | None:
        with self._lock:
            return self._results[-1] if self._results else None

    def new_folder(self) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        d = self.folder / uuid.uuid4().hex[:12]
        d.mkdir()
        return d

    def add(self, result: Result) -> None:
        """Make `result` current; folders of results older than the last KEEP_RESULTS go."""
        with self._lock:
            self._results.append(result)
            dropped, self._results = self._results[:-KEEP_RESULTS], self._results[-KEEP_RESULTS:]
        for old in dropped:
            shutil.rmtree(old.folder, ignore_errors=True)

    def close(self) -> None:
        with self._lock:
            self._results.clear()
        shutil.rmtree(self.folder, ignore_errors=True)
