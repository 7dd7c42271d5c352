import os

import pytest

from salad.files import atomic_write, atomic_write_text, check_writable_dir


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


def test_a_save_killed_between_its_renames_loses_nothing(tmp_path):
    import torch

    from salad.checkpoint import load_checkpoint, save_checkpoint
    ckpt = save_checkpoint(tmp_path / "ckpt", "test", {}, {"model": {"w": torch.full((2,), 3.0)}})
    ckpt.rename(tmp_path / ".ckpt.old-12345")              # the old copy moved aside, the new one never arrived
    (tmp_path / ".ckpt.tmp-12345").mkdir()
    doc, parts = load_checkpoint(tmp_path / "ckpt", kind="test")
    assert parts["model"]["w"].tolist() == [3.0, 3.0]
    save_checkpoint(tmp_path / "ckpt", "test", {}, {"model": {"w": torch.zeros(2)}})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]


def test_training_resumes_from_the_copy_a_killed_save_moved_aside(tmp_path):
    import torch

    from salad.checkpoint import recover_checkpoint, save_checkpoint
    assert not recover_checkpoint(tmp_path / "state")      # nothing to recover: a fresh run
    save_checkpoint(tmp_path / "state", "test", {}, {"model": {"w": torch.zeros(2)}})
    (tmp_path / "state").rename(tmp_path / ".state.old-7")
    (tmp_path / ".state.old-8").mkdir()                    # an empty leftover is not a checkpoint
    assert recover_checkpoint(tmp_path / "state")
    assert (tmp_path / "state" / "config.json").is_file()


def test_reports_name_repository_paths_relative_to_it(tmp_path, monkeypatch):
    from salad.files import REPO_ROOT, shown_path
    assert shown_path(REPO_ROOT / "assets" / "model") == "assets/model"
    monkeypatch.chdir(REPO_ROOT)
    assert shown_path("assets/eval/classifier") == "assets/eval/classifier"
    assert shown_path(tmp_path / "model") == str(tmp_path / "model")     # outside the repository: as given
    assert shown_path("") == ""                                         # none given stays none, not "."


def test_output_folders_are_checked_before_any_work(tmp_path):
    check_writable_dir(tmp_path)
    check_writable_dir(tmp_path / "new" / "deeper")          # made later, on save
    afile = tmp_path / "a.txt"
    afile.write_text("x")
    with pytest.raises(ValueError, match=r"cannot write in .*a\.txt.* is not a directory"):
        check_writable_dir(afile / "sub")
    if os.geteuid() != 0:                                    # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(ValueError, match="not writable"):
            check_writable_dir(locked / "out")
