"""`salad average`: the weight-by-weight mean of consistency students (or denoisers) of one start."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from salad.checkpoint import load_checkpoint, save_checkpoint


@pytest.fixture(scope="module")
def two_students(tiny_student, tmp_path_factory):
    """The tiny student, marked as measured fit for control, and a sibling whose every float weight moved:
    two checkpoints with one config and one teacher, as two fine-tunes of one student are."""
    root = tmp_path_factory.mktemp("average")
    a, b = root / "a", root / "b"
    doc, parts = load_checkpoint(tiny_student / "consistency", kind="denoiser")
    meta = json.loads(json.dumps(doc["meta"]))
    meta["consistency"]["default_for"] = ["control"]
    save_checkpoint(a, "denoiser", doc["config"], parts, meta)
    g = torch.Generator().manual_seed(0)
    moved = {n: {k: t + 0.05 * torch.randn(t.shape, generator=g, dtype=t.dtype) if t.is_floating_point() else t
                 for k, t in tensors.items()} for n, tensors in parts.items()}
    save_checkpoint(b, "denoiser", doc["config"], moved, doc["meta"])
    return a, b


def _model_dir(tiny_student, student, where):
    where.mkdir()
    for part in ("vae", "denoiser"):
        (where / part).symlink_to((tiny_student / part).resolve())
    shutil.copytree(student, where / "consistency")
    return where


def test_the_average_is_the_weighted_mean_and_records_its_inputs(two_students, tmp_path, capsys):
    from salad.cli import main

    a, b = two_students
    assert main(["average", str(a), str(b), "--weights", "0.25", "0.75", "--out", str(tmp_path / "avg")]) == 0
    assert "average written to" in capsys.readouterr().out
    doc, parts = load_checkpoint(tmp_path / "avg", kind="denoiser")
    (doc_a, pa), (doc_b, pb) = load_checkpoint(a), load_checkpoint(b)
    for k, t in parts["denoiser"].items():
        assert t.dtype == pa["denoiser"][k].dtype
        if t.is_floating_point():
            want = 0.25 * pa["denoiser"][k].double() + 0.75 * pb["denoiser"][k].double()
            assert torch.allclose(t.double(), want, atol=1e-6), k
    assert doc["config"] == doc_a["config"]
    assert [(e["path"], e["weight"]) for e in doc["meta"]["average"]] == [(str(a), 0.25), (str(b), 0.75)]
    assert doc["meta"]["average"][1]["sha256"]["denoiser"] == doc_b["files"]["denoiser"]["sha256"]
    # the teacher and guidance range carry over; what a student was measured fit for does not
    assert doc["meta"]["consistency"]["teacher"] == doc_a["meta"]["consistency"]["teacher"]
    assert "default_for" not in doc["meta"]["consistency"]


def test_the_average_samples_and_its_end_weights_are_its_inputs(tiny_student, two_students, tmp_path):
    from salad.pipeline import load_pipeline
    from salad.training.average import average_checkpoints

    a, b = two_students
    average_checkpoints([a, b], [1.0, 0.0], tmp_path / "end")
    average_checkpoints([a, b], None, tmp_path / "mid")
    assert [e["weight"] for e in load_checkpoint(tmp_path / "mid")[0]["meta"]["average"]] == [0.5, 0.5]

    def sample(student, name):
        pipe = load_pipeline(_model_dir(tiny_student, student, tmp_path / name), bf16=False)
        pipe.set_foot_refine(0)
        return pipe.generate("a person walks forward", seconds=2, seed=1, sampler="consistency", steps=2).joints

    only_a, end, mid = sample(a, "ma"), sample(tmp_path / "end", "me"), sample(tmp_path / "mid", "mm")
    assert np.isfinite(mid).all()
    np.testing.assert_allclose(end, only_a, atol=1e-5)
    assert np.abs(mid - only_a).max() > 1e-4


def test_averaging_refuses_what_cannot_correspond(tiny_student, two_students, tmp_path):
    from salad.cli import main
    from salad.training.average import average_checkpoints

    a, b = two_students
    out = tmp_path / "avg"
    with pytest.raises(ValueError, match="architecture, diffusion, text features or VAE differ"):
        average_checkpoints([a, tiny_student / "denoiser"], [0.5, 0.5], out)
    other = tmp_path / "other-teacher"
    doc, parts = load_checkpoint(b)
    doc["meta"]["consistency"]["teacher"]["sha256"] = "0" * 64
    save_checkpoint(other, "denoiser", doc["config"], parts, doc["meta"])
    with pytest.raises(ValueError, match="not distilled from the same teacher"):
        average_checkpoints([a, other], [0.5, 0.5], out)
    with pytest.raises(ValueError, match="at least two"):
        average_checkpoints([a], [1.0], out)
    with pytest.raises(ValueError, match="one weight per checkpoint"):
        average_checkpoints([a, b], [1.0], out)
    with pytest.raises(ValueError, match="sum to 1"):
        average_checkpoints([a, b], [0.7, 0.7], out)
    with pytest.raises(ValueError, match="is one of the checkpoints averaged"):
        average_checkpoints([a, b], [0.5, 0.5], b)
    assert not out.exists()
    assert main(["average", str(a), str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert not out.exists()


def test_integer_tensors_are_kept_when_they_agree_and_refused_when_they_differ(two_students, tmp_path):
    from salad.training.average import average_checkpoints

    def with_counter(src, value, where):
        doc, parts = load_checkpoint(src, kind="denoiser")
        parts["denoiser"]["steps_seen"] = torch.tensor([value], dtype=torch.int64)
        save_checkpoint(where, "denoiser", doc["config"], parts, doc["meta"])
        return where

    a, b = two_students
    a7, b7 = with_counter(a, 7, tmp_path / "a7"), with_counter(b, 7, tmp_path / "b7")
    b8 = with_counter(b, 8, tmp_path / "b8")
    _, parts = load_checkpoint(average_checkpoints([a7, b7], [0.5, 0.5], tmp_path / "avg"), kind="denoiser")
    kept = parts["denoiser"]["steps_seen"]
    assert kept.dtype == torch.int64 and kept.tolist() == [7]
    with pytest.raises(ValueError, match="denoiser/steps_seen: this integer tensor differs"):
        average_checkpoints([a7, b8], [0.5, 0.5], tmp_path / "refused")
    assert not (tmp_path / "refused").exists()


def test_an_average_of_one_recipe_keeps_it_and_distilling_an_average_of_several_is_refused(
        tiny_model, tiny_dataset, tmp_path, capsys):
    """Runs of one training config (their seeds may differ) average into a checkpoint that records that config;
    denoisers trained with different configs record none, and a distillation, which needs the teacher's
    posterior noise, refuses such a teacher rather than guessing it."""
    from salad.cli import main
    from salad.training.average import average_checkpoints

    from conftest import consistency_toml

    doc, parts = load_checkpoint(tiny_model / "denoiser", kind="denoiser")
    meta = json.loads(json.dumps(doc["meta"]))
    reseeded, other = json.loads(json.dumps(meta)), json.loads(json.dumps(meta))
    reseeded["train_config"].setdefault("run", {})["seed"] = 99
    other["train_config"]["posterior_noise"] = 1.0 - float(meta["train_config"].get("posterior_noise", 1.0))
    for name, m in (("seed", reseeded), ("other", other)):
        save_checkpoint(tmp_path / name, "denoiser", doc["config"], parts, m)
    same = average_checkpoints([tiny_model / "denoiser", tmp_path / "seed"], None, tmp_path / "same")
    assert load_checkpoint(same)[0]["meta"]["train_config"] == meta["train_config"]
    teacher = tmp_path / "teacher"
    teacher.mkdir()
    (teacher / "vae").symlink_to((tiny_model / "vae").resolve())
    average_checkpoints([tiny_model / "denoiser", tmp_path / "other"], None, teacher / "denoiser")
    assert "train_config" not in load_checkpoint(teacher / "denoiser")[0]["meta"]
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, teacher, steps=1)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run")]) == 2
    assert "averages denoisers trained with different configs" in capsys.readouterr().err
