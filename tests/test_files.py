import os

import pytest

from salad.files import atomic_write, atomic_write_text


def test_atomic_writes_have_ordinary_permissions_and_leave_nothing_on_failure(tmp_path):
    umask = os.umask(0)
    os.umask(umask)
    p = atomic_write_text(tmp_path / "a" / "report.md", "ok\n")
    assert p.read_text() == "ok\n" and (p.stat().st_mode & 0o777) == (0o666 & ~umask)

    def broken(f):
        f.write(b"half")
        raise RuntimeError("disk full")
    with pytest.raises(RuntimeError):
        atomic_write(p, broken)
    assert p.read_text() == "ok\n" and sorted(x.name for x in p.parent.iterdir()) == ["report.md"]


def test_checkpoints_have_ordinary_permissions(tmp_path):
    import torch

    from salad.checkpoint import save_checkpoint
    umask = os.umask(0)
    os.umask(umask)
    ckpt = save_checkpoint(tmp_path / "ckpt", "test", {}, {"model": {"w": torch.zeros(2)}})
    assert (ckpt.stat().st_mode & 0o777) == (0o777 & ~umask)
    for f in ckpt.iterdir():
        assert (f.stat().st_mode & 0o777) == (0o666 & ~umask), f.name


def test_a_save_clears_what_a_killed_save_left(tmp_path):
    import torch

    from salad.checkpoint import save_checkpoint
    (tmp_path / ".ckpt.tmp-dead").mkdir()                  # a writer killed before its rename
    (tmp_path / ".other.tmp-dead").mkdir()                 # another checkpoint's: not ours to touch
    save_checkpoint(tmp_path / "ckpt", "test", {}, {"model": {"w": torch.zeros(2)}})
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.tmp-dead", "ckpt"]
