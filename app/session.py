"""What one session holds between requests: its latest results of each kind (generation,
edit, guided control, real-motion edit) and what was rendered from them."""
from __future__ import annotations

import shutil
import threading
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

KEEP_RESULTS = 2        # the previous result's files stay while its downloads may still be fetched
CACHE_ENTRIES = 48      # renders kept per result (word x aggregation combinations)
KINDS = ("generate", "edit", "control", "real")


@dataclass
class Result:
    """One finished request: its motion(s), where its files live, and a cache of views rendered from it.

    kind "generate": `motion` with its attention; "edit": `motion` is the edited motion and
    `source` the source one; "control": `motion` and the `signal` it was guided by; "real":
    `motion` is the edited motion, `source` the reconstruction of the `given` input; an edit's
    `params` are its settings as salad resolved them and its timings."""

    request: Any                        # GenerateRequest | EditRequest | ControlRequest | RealEditRequest
    motion: Any                         # salad Motion
    folder: Path
    files: dict[str, Path] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    kind: str = "generate"
    source: Any = None                  # edit: the source Motion
    signal: Any = None                  # control: the ControlSignal
    given: Any = None                   # real: the input (app.real_input.RealInput)
    params: dict[str, Any] = field(default_factory=dict)   # edit, real: salad's EditResult.params
    id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"result kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        self._cache: OrderedDict[tuple, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._making = 0                # cached() calls writing into the folder right now
        self._retired = False           # replaced by newer results: the folder goes once nothing writes to it
        self.reused = 0                 # how often an identical request was answered with this result

    def cached(self, key: tuple, make: Callable[[], Any]) -> Any:
        """The value stored under `key`, made on first use. A cached file that has since
        disappeared (pruned) is made again. Two requests for the same new key may both
        make it; the results are equal, so the last one simply wins. A retired result makes
        nothing new (ResultGone), and its folder outlives every make() already under way."""
        with self._lock:
            if key in self._cache:
                value = self._cache[key]
                if not _missing_file(value):
                    self._cache.move_to_end(key)
                    return value
            if self._retired:
                raise ResultGone(f"this {self.kind} result was replaced by newer ones and its files are gone; "
                                 "run the request again")
            self._making += 1
        try:
            value = make()
        finally:
            with self._lock:
                self._making -= 1
            self._remove_if_retired_and_idle()
        with self._lock:
            self._cache[key] = value
            while len(self._cache) > CACHE_ENTRIES:
                self._cache.popitem(last=False)
        return value

    def retire(self) -> None:
        """Give up the result: its folder goes now, or when the last render into it ends."""
        with self._lock:
            self._retired = True
        self._remove_if_retired_and_idle()

    def _remove_if_retired_and_idle(self) -> None:
        with self._lock:
            remove = self._retired and not self._making
        if remove:
            shutil.rmtree(self.folder, ignore_errors=True)

    def forget(self, key: tuple) -> None:
        """Drop what is stored under `key` (a view of motions that have since changed)."""
        with self._lock:
            self._cache.pop(key, None)

    def peek(self, key: tuple, default: Any = None) -> Any:
        """The value stored under `key` without making it: `default` when there is none yet (or
        its file has since disappeared)."""
        with self._lock:
            value = self._cache.get(key, default)
        return default if value is not default and _missing_file(value) else value

    def intact(self) -> bool:
        """Whether the result is kept and every file of it is still on disk."""
        return not self._retired and self.folder.is_dir() and all(p.exists() for p in self.files.values())


class ResultGone(ValueError):
    """A view asked of a result that newer results have replaced."""


def _missing_file(value) -> bool:
    items = value if isinstance(value, (list, tuple)) else [value]
    return any(isinstance(v, Path) and not v.exists() for v in items)


class Session:
    """A browser tab or API client: its folder and its most recent results of each kind."""

    def __init__(self, key: str, folder: Path):
        self.key, self.folder = key, folder
        self._results: dict[str, list[Result]] = {k: [] for k in KINDS}
        self._lock = threading.Lock()

    @property
    def current(self) -> Result | None:
        """The latest generated motion (the one the Attention tab and the Control tab's
        in-betweening and upper-body edits work on)."""
        return self.latest("generate")

    def latest(self, kind: str) -> Result | None:
        with self._lock:
            results = self._results[kind]
            return results[-1] if results else None

    def new_folder(self) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        d = self.folder / uuid.uuid4().hex[:12]
        d.mkdir()
        return d

    def add(self, result: Result) -> None:
        """Make `result` the latest of its kind; older results (beyond KEEP_RESULTS) retire."""
        with self._lock:
            results = self._results[result.kind]
            results.append(result)
            dropped, self._results[result.kind] = results[:-KEEP_RESULTS], results[-KEEP_RESULTS:]
        for old in dropped:
            old.retire()

    def reuse(self, kind: str, request) -> Result | None:
        """A kept result of an identical request whose files are all still there, made the
        latest of its kind; sampling is deterministic, so running it again would give the same."""
        with self._lock:
            results = self._results[kind]
            for i in range(len(results) - 1, -1, -1):
                r = results[i]
                if r.request == request and r.intact():
                    results.append(results.pop(i))
                    r.reused += 1
                    return r
        return None

    def close(self) -> None:
        with self._lock:
            for results in self._results.values():
                results.clear()
        shutil.rmtree(self.folder, ignore_errors=True)
