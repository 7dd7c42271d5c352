"""The studio's private temp root: one folder per browser/API session, pruned when idle.

Layout: <root>/sessions/<key>/<motion id>/ for the files of each generated motion and
<root>/gradio/ for Gradio's copies of the files it serves. The root belongs to one
process (its pid is written inside) and is removed when the process ends; roots left by
processes that died are removed by the next studio that starts.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

log = logging.getLogger("salad.studio")
ROOT_PREFIX = "salad-studio-"
OWNER_FILE = "owner.pid"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_roots(parent: Path) -> int:
    """Remove studio roots under `parent` whose owning process is gone; returns how many."""
    removed = 0
    for d in parent.glob(f"{ROOT_PREFIX}*"):
        try:
            pid = int((d / OWNER_FILE).read_text().strip())
        except (OSError, ValueError):
            continue                        # not ours, or still being created
        if pid != os.getpid() and not _pid_alive(pid):
            shutil.rmtree(d, ignore_errors=True)
            removed += 1
    return removed


class Workspace:
    """Creates, touches and prunes per-session folders under a fresh private root."""

    def __init__(self, parent: str | os.PathLike | None = None, ttl_s: float = 7200.0):
        parent = Path(parent or tempfile.gettempdir())
        if not parent.is_dir():
            raise ValueError(f"{parent}: the temp folder does not exist")
        remove_stale_roots(parent)
        self.root = Path(tempfile.mkdtemp(prefix=ROOT_PREFIX, dir=parent)).resolve()
        (self.root / OWNER_FILE).write_text(str(os.getpid()))
        self.sessions = self.root / "sessions"
        self.sessions.mkdir()
        self.gradio_cache = self.root / "gradio"
        self.gradio_cache.mkdir()
        self.ttl_s = float(ttl_s)
        self._stop = threading.Event()
        self._janitor: threading.Thread | None = None

    @staticmethod
    def session_key(session_hash: str) -> str:
        # The hash comes from the client: never use it as a path component as it is.
        return hashlib.sha256(str(session_hash).encode("utf-8", "replace")).hexdigest()[:32]

    def session_dir(self, session_hash: str) -> Path:
        """The session's folder (created on demand), marked as just used."""
        d = self.sessions / self.session_key(session_hash)
        d.mkdir(parents=True, exist_ok=True)
        os.utime(d)
        return d

    def remove_session(self, session_hash: str) -> None:
        shutil.rmtree(self.sessions / self.session_key(session_hash), ignore_errors=True)

    def prune(self, now: float | None = None) -> int:
        """Remove session folders not used for longer than the TTL; returns how many."""
        now = time.time() if now is None else now
        removed = 0
        for d in self.sessions.iterdir():
            try:
                idle = now - d.stat().st_mtime
            except FileNotFoundError:
                continue
            if idle > self.ttl_s:
                shutil.rmtree(d, ignore_errors=True)
                removed += 1
        return removed

    def start_janitor(self, every_s: float) -> None:
        """Prune in a daemon thread every `every_s` seconds until close()."""
        def run():
            while not self._stop.wait(every_s):
                try:
                    n = self.prune()
                    if n:
                        log.info("pruned %d idle session folder(s)", n)
                except OSError as exc:       # keep pruning later; a full disk must not stop it
                    log.warning("pruning %s failed: %s", self.sessions, exc)
        self._janitor = threading.Thread(target=run, name="studio-janitor", daemon=True)
        self._janitor.start()

    def close(self) -> None:
        self._stop.set()
        shutil.rmtree(self.root, ignore_errors=True)
