"""Inversion of real motions and editing from the inverted trajectory, on the tiny model."""
import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import synthetic_walk
from salad.diffusion.schedule import NoiseSchedule
from salad.diffusion.inversion import METHODS, ddim_grid, ddim_step, invert, noise_estimate, renoise
from salad.editing.real import decode, edit_inverted, edit_real, encode, reconstruct
from salad.eval.edit_metrics import mpjpe, root_path_deviation, root_path_error
from salad.eval.sdedit import sdedit
from salad.motion.real import load_real_motion
from salad.motion import representation as rep
from salad.pipeline import load_pipeline

PROMPT = "a person walks forward"


@pytest.fixture(scope="module")
def pipe(tiny_model):
    torch.set_num_threads(1)
    return load_pipeline(tiny_model)


@pytest.fixture(scope="module")
def clip(tiny_dataset, pipe):
    name = (tiny_dataset / "test.txt").read_text().split()[0]
    feats = np.load(tiny_dataset / "new_joint_vecs" / f"{name}.npy")
    return load_real_motion(feats, pipe.canvas_frames, trim=True)


@pytest.fixture(scope="module")
def vae_recon(pipe, clip):
    z0 = encode(pipe, clip)
    return z0, decode(pipe, z0, [PROMPT])[0]


def test_ddim_step_is_diffusers_step_and_renoise_undoes_it():
    schedule = NoiseSchedule()
    g = torch.Generator().manual_seed(0)
    for steps in (50, 30):
        grid, sched = ddim_grid(schedule, steps), schedule.sampler("ddim", steps)
        assert grid.timesteps == [int(t) for t in sched.timesteps] and grid.targets[-1] == 0
        x = torch.randn(1, 4, 7, 8, generator=g)
        for i, t in enumerate(sched.timesteps):
            out = torch.randn(x.shape, generator=g)
            ref = sched.step(out, t, x).prev_sample
            mine = ddim_step(schedule, x, out, grid.timesteps[i], grid.targets[i])
            torch.testing.assert_close(mine, ref, atol=2e-5, rtol=1e-4)
            # with the step's own noise estimate, renoise goes back exactly
            eps = noise_estimate(schedule, x, out, grid.timesteps[i])
            back = renoise(schedule, mine, eps, grid.timesteps[i], grid.targets[i])
            torch.testing.assert_close(back, x, atol=1e-4, rtol=1e-4)
            x = mine


def test_fixed_point_inversion_round_trip_beats_plain_ddim(pipe, clip, vae_recon):
    z0, vae = vae_recon
    exact = invert(pipe, z0, PROMPT, method="fixed_point", steps=8)
    assert exact.trajectory.shape == (9,) + tuple(z0.shape) and torch.equal(exact.z0, z0)
    rec = reconstruct(pipe, exact)
    assert rec.frames == clip.frames
    assert rec.info["latent_error"] < 0.01
    assert mpjpe(rec.joints, vae.joints) < 0.005
    # textbook DDIM inversion at cfg 1 sampled back at cfg 7.5 lands far from the latent...
    plain = invert(pipe, z0, PROMPT, method="ddim", steps=8)
    drift = reconstruct(pipe, plain)
    assert drift.info["latent_error"] > 5 * rec.info["latent_error"]
    # ...unless the per-step corrections pull it onto its trajectory: then it is the VAE's reconstruction
    fixed = reconstruct(pipe, plain, correct=True)
    assert fixed.info["latent_error"] < 1e-5
    np.testing.assert_allclose(fixed.joints, vae.joints, atol=1e-3)


def test_negative_prompt_and_null_text_inversions_reconstruct(pipe, vae_recon):
    z0, vae = vae_recon
    plain = reconstruct(pipe, invert(pipe, z0, PROMPT, method="ddim", steps=6))
    negative = reconstruct(pipe, invert(pipe, z0, PROMPT, method="negative", steps=6))
    null = invert(pipe, z0, PROMPT, method="null_text", steps=6, inner=4)
    assert len(null.uncond) == 6 and null.info["model_calls"] > 6
    nt = reconstruct(pipe, null)
    assert negative.info["latent_error"] < plain.info["latent_error"]
    assert nt.info["latent_error"] < plain.info["latent_error"]
    # the optimisation leaves the denoiser's weights as they were
    assert all(not p.requires_grad or p.grad is None for p in pipe.denoiser.parameters())


def test_edit_source_branch_is_the_reconstruction(pipe, vae_recon):
    z0, vae = vae_recon
    inv = invert(pipe, z0, PROMPT, method="negative", steps=5)
    res = edit_inverted(pipe, inv, mode="mirror", mirror="all")
    np.testing.assert_allclose(res.source.joints, vae.joints, atol=1e-3)
    assert res.edited.frames == res.source.frames == vae.frames
    assert res.params["inversion"] == "negative" and res.params["correct"] is True
    assert res.edited.attention.words == ["a", "person", "walks", "forward"]
    swap = edit_inverted(pipe, inv, "a person runs forward", mode="swap", tau=0.5)
    np.testing.assert_allclose(swap.source.joints, vae.joints, atol=1e-3)
    assert np.abs(swap.edited.joints - swap.source.joints).max() > 1e-3
    loose = edit_inverted(pipe, inv, "a person runs forward", mode="swap", correct=False)
    np.testing.assert_allclose(loose.source.joints, reconstruct(pipe, inv).joints, atol=1e-4)
    assert loose.edited.text == "a person runs forward"


def test_edit_real_from_bvh_with_retargeting(pipe, tmp_path):
    from salad.motion.bvh import save_bvh
    path = tmp_path / "walk.bvh"
    save_bvh(path, synthetic_walk(37, seed=5), fps=20)
    lengths = rep.bone_lengths(synthetic_walk(37, seed=5)) * 1.1
    res = edit_real(pipe, path, PROMPT, mode="reweight", reweight={"walks": 2.0}, steps=4, inversion="fixed_point",
                    bone_lengths=lengths)
    assert res.params["retargeted"] is True and res.params["input_frames"] == 36
    assert res.edited.frames == 36 and np.isfinite(res.edited.joints).all()
    assert res.source.info["mpjpe_m"] >= 0 and res.params["inversion_seconds"] > 0
    real = load_real_motion(path, pipe.canvas_frames, lengths)
    np.testing.assert_allclose(rep.bone_lengths(real.joints)[1:], lengths[1:], atol=5e-3)


@pytest.mark.parametrize("motion, match", [
    (np.zeros((30, 21, 3)), "expected joints"),
    (np.zeros((30, 100)), "expected joints"),
    (np.full((30, 263), np.nan), "NaN"),
    (np.zeros((12, 263)), "too short"),
    (np.zeros((10, 22, 3)), "too short"),
    (np.array([["a"] * 263] * 30), "numeric"),
    (42, "BVH/NPY path"),
])
def test_edit_real_rejects_bad_arrays(pipe, motion, match):
    with pytest.raises(ValueError, match=match):
        pipe.edit_real(motion, PROMPT, mode="mirror", steps=2)


def test_edit_real_rejects_bad_files_and_settings(pipe, tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.bvh"):
        edit_real(pipe, tmp_path / "missing.bvh", PROMPT, mode="mirror", steps=2)
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{ nonsense")
    with pytest.raises(ValueError, match="bad.bvh"):
        edit_real(pipe, bad, PROMPT, mode="mirror", steps=2)
    txt = tmp_path / "motion.txt"
    txt.write_text("1 2 3")
    with pytest.raises(ValueError, match="unsupported input"):
        edit_real(pipe, txt, PROMPT, mode="mirror", steps=2)
    long = np.zeros((pipe.canvas_frames + 8, 263), np.float32)
    with pytest.raises(ValueError, match="longer than"):
        edit_real(pipe, long, PROMPT, mode="mirror", steps=2)
    trimmed = load_real_motion(long, pipe.canvas_frames, trim=True)
    assert trimmed.frames == pipe.canvas_frames and trimmed.info["trimmed_from_frames"] == len(long)
    feats = np.zeros((30, 263), np.float32)
    with pytest.raises(ValueError, match="mode must be one of"):
        edit_real(pipe, feats, PROMPT, mode="bogus")
    with pytest.raises(ValueError, match="swap needs a target"):
        edit_real(pipe, feats, PROMPT, mode="swap")
    with pytest.raises(ValueError, match="inversion must be one of"):
        edit_real(pipe, feats, PROMPT, mode="mirror", inversion="bogus")
    with pytest.raises(ValueError, match="steps"):
        edit_real(pipe, feats, PROMPT, mode="mirror", steps=0)
    with pytest.raises(ValueError, match="strength"):
        sdedit(pipe, feats, PROMPT, strength=1.5)
    z0 = encode(pipe, load_real_motion(feats, pipe.canvas_frames))
    with pytest.raises(ValueError, match="iterations"):
        invert(pipe, z0, PROMPT, "fixed_point", iterations=0)
    with pytest.raises(ValueError, match="one latent"):
        invert(pipe, z0[0], PROMPT, "negative")
    with pytest.raises(ValueError, match="bone_lengths must be 22"):
        edit_real(pipe, synthetic_walk(30), PROMPT, mode="mirror", steps=2, bone_lengths=[0.1, 0.2])
    skeleton = tmp_path / "skeleton.json"
    skeleton.write_text(json.dumps({"bone_lengths_m": [0.1] * 5}))
    with pytest.raises(ValueError, match="skeleton.json"):
        edit_real(pipe, synthetic_walk(30), PROMPT, mode="mirror", steps=2, bone_lengths=skeleton)


def test_sdedit_keeps_more_of_the_input_at_low_strength(pipe, clip, vae_recon):
    _, vae = vae_recon
    weak = sdedit(pipe, clip, "a person turns left while walking", strength=0.1, steps=10)
    strong = sdedit(pipe, clip, "a person turns left while walking", strength=0.9, steps=10)
    assert weak.frames == strong.frames == clip.frames
    assert mpjpe(weak.joints, vae.joints) < mpjpe(strong.joints, vae.joints)


def test_path_deviation_ignores_speed_along_the_path():
    fast, slow = synthetic_walk(40, speed=1.2), synthetic_walk(40, speed=0.6)
    assert root_path_error(slow, fast) > 0.2
    assert root_path_deviation(slow, fast) < 0.01
    aside = fast.copy()
    aside[..., 0] += 0.3
    assert root_path_deviation(aside, fast) == pytest.approx(0.3, abs=1e-4)
    assert mpjpe(aside, fast) == pytest.approx(0.0, abs=1e-6) and mpjpe(aside, fast, root_relative=False) > 0.29


def _cli(add_parser, argv):
    p = argparse.ArgumentParser(prog="salad")
    add_parser(p.add_subparsers(dest="command", required=True))
    a = p.parse_args(argv)
    return a.func(a)


def test_edit_real_command(tiny_model, tmp_path, capsys):
    from salad.cli.edit import add_edit_real as add_parser
    inp = tmp_path / "in.npy"
    np.save(inp, synthetic_walk(41, seed=2))
    out_bvh, out_npy, rec = tmp_path / "out.bvh", tmp_path / "out.npy", tmp_path / "rec.npz"
    assert _cli(add_parser, ["edit-real", str(inp), "--source", PROMPT, "--target", "a person runs forward",
                             "-o", str(out_bvh), "-o", str(out_npy), "--reconstruction", str(rec), "--steps", "3",
                             "--inversion", "negative", "--model", str(tiny_model)]) == 0
    assert np.load(out_npy).shape == (40, 22, 3)
    assert out_bvh.read_text().startswith("HIERARCHY") and np.load(rec)["features"].shape == (40, 263)
    from salad.motion.bvh import load_bvh
    assert load_bvh(out_bvh).scale == 0.01                           # centimetres unless --bvh-units m
    assert "reconstruction MPJPE" in capsys.readouterr().out
    with pytest.raises(ValueError, match="unsupported output"):
        _cli(add_parser, ["edit-real", str(inp), "--source", PROMPT, "--mode", "mirror", "-o", str(tmp_path / "x.txt"),
                          "--model", str(tiny_model)])
    with pytest.raises(ValueError, match="--side-by-side; use .mp4"):
        _cli(add_parser, ["edit-real", str(inp), "--source", PROMPT, "--mode", "mirror", "-o", str(out_npy),
                          "--side-by-side", str(tmp_path / "sbs.gif"), "--model", str(tiny_model)])


def _labelled_dataset(root: Path) -> Path:
    from salad.data.captions import caption_line, captions_for
    for sub in ("new_joint_vecs", "texts"):
        (root / sub).mkdir(parents=True)
    labels = {}
    for i, (content, style) in enumerate((("wave-left-hand", "normal"), ("walk", "normal"), ("walk", "happy"))):
        name = f"c{i}"
        np.save(root / "new_joint_vecs" / f"{name}.npy",
                rep.joints_to_features(synthetic_walk(60, seed=i)).astype(np.float32))
        caps = captions_for(content, style, name)
        (root / "texts" / f"{name}.txt").write_text("\n".join(caption_line(c) for c in caps) + "\n")
        labels[name] = {"content": content, "style": style, "mirrored": False, "split": "test"}
    (root / "test.txt").write_text("\n".join(labels) + "\n")
    (root / "labels.json").write_text(json.dumps(labels))
    return root


def test_eval_real_edit_end_to_end(tiny_model, tmp_path):
    from salad.eval.classifiers import ClassifierConfig, MotionClassifier, save_classifier
    from salad.data.labels import SIDES
    from salad.eval.networks import MotionEncoderConfig
    from salad.cli.eval import add_eval_real_edit as add_parser

    data = _labelled_dataset(tmp_path / "data")
    torch.manual_seed(0)
    cfg = ClassifierConfig(motion=MotionEncoderConfig(conv_channels=8, gru_hidden=8, output_dim=8),
                           classes={"content": ["walk", "wave-left-hand", "wave-right-hand"],
                                    "style": ["exhausted", "happy", "normal"], "side": list(SIDES)})
    save_classifier(tmp_path / "clf", MotionClassifier(cfg), np.zeros(263), np.ones(263))
    out = tmp_path / "report"
    assert _cli(add_parser, ["eval-real-edit", "--data", str(data), "--classifier", str(tmp_path / "clf"),
                             "--out", str(out), "--model", str(tiny_model), "--clips", "2", "--edit-clips", "1",
                             "--methods", ",".join(METHODS), "--edit-methods", "fixed_point", "--sdedit", "0.5",
                             "--steps", "3"]) == 0
    res = json.loads((out / "results.json").read_text())
    fid = res["fidelity"]["summary"]
    assert set(fid) == {"vae", *METHODS} and fid["vae"]["clips"] == 2
    assert all(fid[m]["mpjpe_m"] >= 0 and fid[m]["invert_s"] > 0 for m in METHODS)
    assert res["mirror"]["clips"] == ["c0"] and res["style"]["clips"] == ["c1"]
    mirror = res["mirror"]["summary"]
    assert set(mirror) == {"input", "vae", "geometric mirror", "inversion fixed_point", "sdedit 0.5"}
    assert mirror["geometric mirror"]["mpjpe_to_mirror_m"] == 0.0
    assert mirror["input"]["root_path_deviation_m"] == 0.0 and "foot_skating_ratio" in mirror["sdedit 0.5"]
    # with corrections the source branch of the edit is the VAE's reconstruction
    vae_err = res["mirror"]["per_clip"][0]["variants"]["vae"]["mpjpe_to_input_m"]
    assert mirror["inversion fixed_point"]["source_branch_mpjpe_m"] == pytest.approx(vae_err, abs=1e-3)
    assert 0 <= res["style"]["summary"]["sdedit 0.5"]["success"] <= 1
    report = (out / "report.md").read_text()
    assert "Inversion fidelity" in report and "| fixed_point |" in report and "sdedit 0.5" in report
    with pytest.raises(ValueError, match="unknown inversion method"):
        _cli(add_parser, ["eval-real-edit", "--data", str(data), "--classifier", str(tmp_path / "clf"),
                          "--out", str(out), "--model", str(tiny_model), "--methods", "bogus"])
