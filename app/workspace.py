"""The studio's private temp root: one folder per browser/API session, pruned when idle.

Layout: <root>/sessions/<key>/<motion id>/ for the files of each generated motion and
<root>/gradio/ for Gradio's copies of the files it serves (<content hash>/<name>) and of the
files users upload. The root belongs to one process (its pid is written inside) and is
removed when the process ends; roots left by processes that died are removed by the next
studio that starts.
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
from typing import Callable

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

    def __init__(self, parent: str | os.PathLike | None = None, ttl_s: float = 7200.0,
                 cache_key: Callable[[Path], str] | None = None):
        """`cache_key(file)`: the folder under gradio_cache that holds the served copy of a file
        (Gradio names it by a hash of the content); None: served copies are left to Gradio."""
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
        self.cache_key = cache_key
        self._uploads: dict[str, set[Path]] = {}     # session key -> uploaded files its requests used
        self._lock = threading.Lock()
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

    def note_upload(self, session_hash: str, path) -> None:
        """Remember that the session used the uploaded file `path` (one under gradio_cache), so that
        it goes with the session."""
        try:
            p = Path(path).resolve()
            p.relative_to(self.gradio_cache)
        except (TypeError, ValueError, OSError):
            return
        with self._lock:
            self._uploads.setdefault(self.session_key(session_hash), set()).add(p)

    def remove_session(self, session_hash: str) -> None:
        """The session has ended: its folder goes, and with it the copies Gradio serves of its files
        and the files it uploaded, unless another session holds the same content."""
        key = self.session_key(session_hash)
        folder = self.sessions / key
        with self._lock:
            uploads = self._uploads.pop(key, set())
            kept = set().union(*self._uploads.values())
        for d in self._served_copies(folder):
            shutil.rmtree(d, ignore_errors=True)
        for up in uploads - kept:
            up.unlink(missing_ok=True)
            try:
                up.parent.rmdir()
            except OSError:         # not empty, or already gone
                pass
        shutil.rmtree(folder, ignore_errors=True)

    def _served_copies(self, folder: Path) -> list[Path]:
        """The folders under gradio_cache holding served copies of the files in `folder` and of no
        other session's file. Only other files of a size one of ours has can share our content,
        so only those are hashed."""
        if self.cache_key is None or not folder.is_dir():
            return []
        mine = _files(folder)
        sizes = {size for _, size in mine}
        try:
            others = [d for d in self.sessions.iterdir() if d != folder]
        except OSError:
            others = []
        shared = {self._key(p) for d in others for p, size in _files(d) if size in sizes}
        found = []
        for p, _ in mine:
            key = self._key(p)
            if key is not None and key not in shared and (self.gradio_cache / key).is_dir():
                found.append(self.gradio_cache / key)
        return found

    def _key(self, path: Path) -> str | None:
        try:
            return self.cache_key(path)
        except OSError:             # removed meanwhile
            return None

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


def _files(folder: Path) -> list[tuple[Path, int]]:
    """(file, size) of every file under `folder` that is still there when looked at."""
    out = []
    for p in folder.rglob("*"):
        try:
            if p.is_file():
                out.append((p, p.stat().st_size))
        except OSError:
            continue
    return out
