"""Atomic file writes: a file appears complete under its name, or not at all; and the check that an output
folder can be written, made before the work that ends by writing there."""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

# Relative paths in configs and checkpoint metadata (a VAE's training data, say) are read against the checkout.
REPO_ROOT = Path(__file__).resolve().parent.parent

# mkstemp creates files 0600; outputs should get the permissions any new file of this process gets
_UMASK = os.umask(0)
os.umask(_UMASK)


def ordinary_permissions(path: str | Path) -> None:
    """Give a file or directory made by mkstemp/mkdtemp (0600/0700) the permissions a plain new one gets."""
    os.chmod(path, (0o777 if Path(path).is_dir() else 0o666) & ~_UMASK)


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of `path` (same suffix) to write; it replaces `path` only if
    the block finishes, and is removed otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".part{path.suffix}")
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        ordinary_permissions(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write(path: str | Path, write: Callable) -> Path:
    """Call write(binary file object) on a temporary sibling, flush it to disk, then rename."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write a UTF-8 text file (LF line ends) atomically."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def shown_path(path: str | Path) -> str:
    """A path as a report shows it: relative to the repository when inside it ("" stays "": none given)."""
    if not str(path):
        return ""
    p = Path(path).resolve()
    return str(p.relative_to(REPO_ROOT)) if p.is_relative_to(REPO_ROOT) else str(path)


def check_writable_dir(path: str | Path) -> None:
    """Raise ValueError unless `path` is a folder this process can write in, or one it can make (its nearest
    existing ancestor is such a folder)."""
    existing = Path(path).absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"cannot write in {path}: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write in {path}: {existing} is not writable (permission denied)")
