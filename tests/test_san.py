import json
import os
import shutil

import numpy as np
import pytest
import torch

from salad.checkpoint import CheckpointError
from salad.config import ConfigError
from salad.models.discriminator import (DiscriminatorConfig, PromptDiscriminator, SANDiscriminator,
                                        san_discriminator_loss, san_generator_loss)
from salad.models.io import load_vae, save_vae, vae_checksum, vae_latent_checksums, vae_latent_sources
from salad.pipeline import load_pipeline
from salad.training.configs import DataConfig, OptimConfig, RunConfig, VAESANTrainConfig
from salad.training.loop import Trainer
from salad.training.vae_adv_task import VAESANTask, encoder_state

SMALL = DiscriminatorConfig(width=16, levels=2, blocks_per_level=1)


def test_the_prompt_discriminator_judges_frames_given_the_prompt():
    """Any latent length (padded to whole patches), frames past a motion's end not judged, and the
    prompt changes the verdict on the same motion."""
    torch.manual_seed(0)
    d = PromptDiscriminator(frame_dim=28, text_dim=12, config=SMALL)
    z, pooled = torch.randn(2, 11, 7, 4), torch.randn(2, 12)
    valid = torch.arange(11)[None] < torch.tensor([[11], [6]])
    logits = d(z, pooled, valid)
    assert logits.shape == (2, 3) and d.patch_mask(z, valid).tolist() == [[True] * 3, [True, True, False]]
    later = z.clone()
    later[1, 6:] = torch.randn(5, 7, 4)
    assert torch.equal(d(later, pooled, valid)[1], logits[1])
    assert not torch.allclose(d(z, pooled.flip(0), valid), logits)
    out = d.san_logits(z, pooled, valid)
    assert torch.allclose(out.hinge, logits) and torch.allclose(out.direction, logits)


def test_direction_is_unit_norm_and_the_two_terms_update_orthogonal_parts():
    torch.manual_seed(0)
    d = SANDiscriminator(SMALL)
    with torch.no_grad():
        d.weight.mul_(7.0)
    assert torch.allclose(d.direction().norm(), torch.tensor(1.0))
    x = torch.randn(3, 16, 263)
    # the generator's logits are the inner product with the unit direction, times |w|
    h = d.features(x.transpose(1, 2))
    assert torch.allclose(d(x), torch.einsum("bct,c->bt", h, d.weight), atol=1e-5)

    out = d.san_logits(x)
    g_hinge, = torch.autograd.grad(out.hinge.sum(), d.weight, retain_graph=True)
    g_dir, = torch.autograd.grad(out.direction.sum(), d.weight)
    w = d.weight.detach()
    cos = lambda a, b: float(torch.dot(a, b) / (a.norm() * b.norm()))
    assert abs(cos(g_hinge, w)) > 0.999          # hinge: only the scale |w| (radial)
    assert abs(cos(g_dir, w)) < 1e-4             # Wasserstein: only the direction (tangential)
    # the feature map learns from the hinge term alone
    conv = d.features[0].weight
    assert torch.autograd.grad(d.san_logits(x).direction.sum(), conv, allow_unused=True)[0] is None
    assert torch.autograd.grad(d.san_logits(x).hinge.sum(), conv)[0].abs().sum() > 0


def test_discriminator_separates_a_toy_problem_and_the_generator_gradient_points_to_real():
    torch.manual_seed(0)
    d = SANDiscriminator(SMALL)
    opt = torch.optim.Adam(d.parameters(), lr=2e-3, betas=(0.5, 0.9))
    shift = torch.zeros(263)
    shift[:20] = 1.0
    real_batch = lambda: torch.randn(16, 16, 263) * 0.5 + shift
    fake_batch = lambda: torch.randn(16, 16, 263) * 0.5 - shift
    for _ in range(25):
        loss, logs = san_discriminator_loss(d.san_logits(real_batch()), d.san_logits(fake_batch()))
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        r, f = d(real_batch()), d(fake_batch())
    assert r.mean() > 0.5 and f.mean() < -0.5 and logs["d_gap"] > 1.0
    fake = fake_batch().requires_grad_(True)
    grad, = torch.autograd.grad(san_generator_loss(d(fake)), fake)
    step = -grad.mean(dim=(0, 1))
    assert torch.dot(step, shift) > 0            # descending the generator loss moves fakes towards real


def test_padding_patches_are_masked_out():
    d = SANDiscriminator(SMALL)
    valid = torch.zeros(2, 16, dtype=torch.bool)
    valid[0, :9] = True
    valid[1, :] = True
    assert d.patch_mask(valid).tolist() == [[True, True, True, False], [True] * 4]
    x = torch.randn(2, 16, 263)
    y = x.clone()
    y[0, 9:] = 100.0                               # garbage after the end must not matter
    assert torch.equal(d(x, valid), d(y, valid))
    with pytest.raises(ValueError, match="divisible by 4"):
        d(torch.randn(1, 10, 263))


def _san_cfg(tiny_dataset, source, out, steps=2, lam=1e-3):
    return VAESANTrainConfig(
        vae=str(source), lambda_adv=lam, data=DataConfig(root=str(tiny_dataset), window=16),
        discriminator=SMALL, optim=OptimConfig(lr=1e-3, warmup_steps=1, batch_size=4, max_steps=steps, grad_clip=0.0),
        run=RunConfig(out_dir=str(out), bf16=True, checkpoint_every=2, log_every=1))


def test_fine_tuning_keeps_the_encoder_bit_identical_and_the_denoiser_compatible(tiny_model, tiny_dataset, tmp_path):
    source = tiny_model / "vae"
    before, _, scale, _ = load_vae(source)
    task = VAESANTask(_san_cfg(tiny_dataset, source, tmp_path / "run"))
    disc0 = {k: v.clone() for k, v in task.model.disc.state_dict().items()}
    trainer = Trainer(task, task.cfg.optim, task.cfg.run)
    out = trainer.fit()
    after, _, new_scale, doc = load_vae(out)
    enc0, enc1 = encoder_state(before), encoder_state(after)
    assert enc0 and all(torch.equal(enc0[k], enc1[k]) for k in enc0)
    changed = [k for k, v in after.state_dict().items() if k not in enc0 and not torch.equal(v, before.state_dict()[k])]
    assert changed, "the decoder did not train"
    assert any(not torch.equal(v, disc0[k]) for k, v in task.model.disc.state_dict().items())
    assert new_scale == scale
    log = [json.loads(l) for l in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert {"g_adv", "d_loss", "d_gap", "rec"} <= set(log[-1])

    src_sum = vae_checksum(source)
    assert doc["config"]["latent_source_sha256"] == src_sum
    assert vae_latent_sources(out) == [src_sum, vae_checksum(out)]
    model = tmp_path / "model"
    model.mkdir()
    os.symlink(out, model / "vae")
    os.symlink((tiny_model / "denoiser").resolve(), model / "denoiser")
    assert load_pipeline(model).vae is not None            # the denoiser recorded the source's checksum

    # resuming continues the same run; a later fine-tune of the fine-tune keeps the lineage
    resumed = Trainer(VAESANTask(_san_cfg(tiny_dataset, source, tmp_path / "run", steps=3)), task.cfg.optim, task.cfg.run)
    assert resumed.try_resume() and resumed.step_count == 2
    second = Trainer(VAESANTask(_san_cfg(tiny_dataset, out, tmp_path / "run2", steps=2)), task.cfg.optim,
                     RunConfig(out_dir=str(tmp_path / "run2"), bf16=False, checkpoint_every=2)).fit()
    assert vae_latent_checksums(second) == {src_sum, vae_checksum(out), vae_checksum(second)}


def test_a_vae_with_another_latent_space_is_refused(tiny_model, tmp_path):
    vae, norm, scale, _ = load_vae(tiny_model / "vae")
    with torch.no_grad():
        vae.to_dist.weight.add_(0.01)
    model = tmp_path / "model"
    save_vae(model / "vae", vae, norm, scale)
    shutil.copytree((tiny_model / "denoiser").resolve(), model / "denoiser")
    with pytest.raises(CheckpointError, match="different VAE"):
        load_pipeline(model)
    # a forged lineage entry that is not a string is a clear error, not a silent pass
    cfg_file = model / "vae" / "config.json"
    doc = json.loads(cfg_file.read_text())
    doc["config"]["latent_lineage_sha256"] = [123]
    cfg_file.write_text(json.dumps(doc))
    with pytest.raises(CheckpointError, match="malformed"):
        vae_latent_checksums(model / "vae")


def test_lambda_zero_trains_no_discriminator(tiny_model, tiny_dataset, tmp_path):
    task = VAESANTask(_san_cfg(tiny_dataset, tiny_model / "vae", tmp_path / "ctl", steps=1, lam=0.0))
    disc0 = {k: v.clone() for k, v in task.model.disc.state_dict().items()}
    trainer = Trainer(task, task.cfg.optim, task.cfg.run)
    logs = trainer.step(task.batch(trainer.rng))
    assert "g_adv" not in logs and logs["loss"] == pytest.approx(logs["rec_total"])
    # latents are encoded as the denoiser sees them (no encoder dropout); the decoder trains as usual
    assert not task.model.vae.enc22.training and not task.model.vae.to_dist.training
    assert task.model.vae.dec22.training
    assert all(torch.equal(v, disc0[k]) for k, v in task.model.disc.state_dict().items())
    with pytest.raises(ValueError, match="lambda_adv"):
        VAESANTask(_san_cfg(tiny_dataset, tiny_model / "vae", tmp_path / "bad", lam=-1.0))


def test_a_widened_decoder_decodes_as_before_then_trains_and_loads_with_its_width(tiny_model, tiny_dataset, tmp_path):
    from salad.models.vae import widen_decoder
    source = tiny_model / "vae"
    vae, _, _, _ = load_vae(source)
    dim = vae.decoder_dim
    wide = widen_decoder(vae, dim + 8).eval()
    z = torch.randn(2, 6, 7, vae.config.latent_dim)
    with torch.no_grad():
        (a, act_a), (b, act_b) = vae.decode(z), wide.decode(z)
    assert torch.allclose(a, b, atol=1e-5) and torch.allclose(act_a, act_b, atol=1e-5)
    assert sum(p.numel() for p in wide.parameters()) > sum(p.numel() for p in vae.parameters())
    enc = encoder_state(vae)
    assert all(torch.equal(v, wide.state_dict()[k]) for k, v in enc.items())
    with pytest.raises(ValueError, match="narrow"):
        widen_decoder(wide, dim)

    cfg = _san_cfg(tiny_dataset, source, tmp_path / "wide", steps=2)
    cfg.decoder_dim = dim + 8
    out = Trainer(VAESANTask(cfg), cfg.optim, cfg.run).fit()
    trained, _, _, doc = load_vae(out)
    assert trained.decoder_dim == dim + 8 and doc["config"]["vae"]["decoder_dim"] == dim + 8
    # the feature heads' weights on the new channels start at zero and training moved them
    assert torch.equal(wide.joint_out.nets[0][2].weight[:, dim:], torch.zeros_like(wide.joint_out.nets[0][2].weight[:, dim:]))
    assert trained.joint_out.nets[0][2].weight[:, dim:].abs().sum() > 0
    assert all(torch.equal(v, trained.state_dict()[k]) for k, v in enc.items())
    cfg.decoder_dim = dim - 1
    with pytest.raises(ConfigError, match="narrower"):
        VAESANTask(cfg)


def test_planted_foot_error_counts_sliding_where_the_real_foot_is_planted_only(tiny_dataset):
    import numpy as np

    from salad.motion import representation as rep
    from salad.training.foot_loss import planted_foot_error, velocity_errors

    norm = rep.Normalizer(np.load(tiny_dataset / "Mean.npy"), np.load(tiny_dataset / "Std.npy"))
    f = np.load(tiny_dataset / "new_joint_vecs" / "000000.npy").astype(np.float64)
    as_batch = lambda x: torch.from_numpy(norm.normalize(x)).float()[None]
    valid = torch.ones(1, len(f), dtype=torch.bool)
    planted = f[:-1, rep.CONTACT_SLICE] > 0.5
    assert planted.any() and not planted.all()          # a walk: feet plant and swing

    assert float(planted_foot_error(as_batch(f), as_batch(f), valid, norm)) == pytest.approx(0.0, abs=1e-6)
    # the whole body drifting sideways at 0.2 m/s: every foot slides by (0.2 m/s)^2 where it should stand
    slid = f.copy()
    slid[:, 1] += 0.2 / rep.FPS
    assert float(planted_foot_error(as_batch(slid), as_batch(f), valid, norm)) == pytest.approx(0.04, rel=0.02)
    # the root drifts with it, on every frame: the root term sees the same (0.2 m/s)^2
    assert float(velocity_errors(as_batch(slid), as_batch(f), valid, norm)["root"]) == pytest.approx(0.04, rel=0.02)
    # a steady drift has no acceleration; a root trembling by +-1 mm a frame has 4 mm * FPS^2 on every
    # frame, on 1 of the 22 joints
    assert float(velocity_errors(as_batch(slid), as_batch(f), valid, norm)["accel"]) == pytest.approx(0.0, abs=0.05)
    trembling = f.copy()
    trembling[:, 3] += 0.001 * (-1.0) ** np.arange(len(f))
    expected = (4 * 0.001 * rep.FPS ** 2) ** 2 / 22
    assert float(velocity_errors(as_batch(trembling), as_batch(f), valid, norm)["accel"]) == pytest.approx(expected, rel=0.05)
    # a row weighted 0 counts for nothing
    two = velocity_errors(torch.cat((as_batch(slid), as_batch(f))), torch.cat((as_batch(f), as_batch(f))),
                          torch.cat((valid, valid)), norm, weights=torch.tensor([0.0, 1.0]))
    assert float(two["foot"]) == pytest.approx(0.0, abs=1e-6) and float(two["root"]) == pytest.approx(0.0, abs=1e-6)
    assert float(two["accel"]) == pytest.approx(0.0, abs=0.05)
    # with no planted frame in the real motion there is nothing to count
    real_no_contact = f.copy()
    real_no_contact[:, rep.CONTACT_SLICE] = 0.0
    assert float(planted_foot_error(as_batch(slid), as_batch(real_no_contact), valid, norm)) == 0.0
    # frames past a motion's end (valid = False) are not counted either
    assert float(planted_foot_error(as_batch(slid), as_batch(f), torch.zeros_like(valid), norm)) == 0.0


def test_the_bone_error_is_the_squared_change_of_each_bones_length(tiny_dataset):
    import numpy as np

    from salad.motion import representation as rep
    from salad.training.foot_loss import bone_error

    norm = rep.Normalizer(np.load(tiny_dataset / "Mean.npy"), np.load(tiny_dataset / "Std.npy"))
    f = np.load(tiny_dataset / "new_joint_vecs" / "000000.npy").astype(np.float64)
    as_batch = lambda x: torch.from_numpy(norm.normalize(x)).float()[None]
    valid = torch.ones(1, len(f), dtype=torch.bool)
    assert float(bone_error(as_batch(f), as_batch(f), valid, norm)) == pytest.approx(0.0, abs=1e-8)
    # the right ankle and toes drawn 5 cm up the shin: the shin is 5 cm short in every frame, the foot keeps its
    # length, and the error is that one bone's 0.05^2 shared among the 21 bones
    ric = lambda joint: slice(4 + 3 * (joint - 1), 4 + 3 * joint)
    knee, ankle, toe = 5, 8, 11
    shin = f[:, ric(ankle)] - f[:, ric(knee)]
    pull = 0.05 * shin / np.linalg.norm(shin, axis=-1, keepdims=True)
    short = f.copy()
    short[:, ric(ankle)] -= pull
    short[:, ric(toe)] -= pull
    assert float(bone_error(as_batch(short), as_batch(f), valid, norm)) == pytest.approx(0.05 ** 2 / 21, rel=0.02)
    # frames past a motion's end (valid = False) are not counted
    assert float(bone_error(as_batch(short), as_batch(f), torch.zeros_like(valid), norm)) == 0.0


def test_the_foot_term_joins_the_decoders_loss(tiny_model, tiny_dataset, tmp_path):
    cfg = _san_cfg(tiny_dataset, tiny_model / "vae", tmp_path / "foot", steps=1, lam=0.0)
    cfg.lambda_foot, cfg.lambda_root, cfg.lambda_acc, cfg.lambda_bone = 2.0, 3.0, 0.1, 5.0
    task = VAESANTask(cfg)
    trainer = Trainer(task, task.cfg.optim, task.cfg.run)
    logs = trainer.step(task.batch(trainer.rng))
    assert logs["foot"] > 0 and logs["root_vel"] > 0 and logs["accel"] > 0 and logs["bone"] > 0
    assert logs["loss"] == pytest.approx(logs["rec_total"] + 2.0 * logs["foot"] + 3.0 * logs["root_vel"]
                                         + 0.1 * logs["accel"] + 5.0 * logs["bone"], rel=1e-5)
    for name in ("lambda_foot", "lambda_acc", "lambda_bone"):
        bad = _san_cfg(tiny_dataset, tiny_model / "vae", tmp_path / name, steps=1, lam=0.0)
        setattr(bad, name, -1.0)
        with pytest.raises(ValueError, match=name):
            VAESANTask(bad)


def test_eval_vae_measures_pose_error_and_feet_for_each_vae(tiny_model, tiny_dataset, tmp_path, capsys):
    import numpy as np

    from salad.cli import main
    from salad.eval.physics import still_foot_share
    from salad.motion import representation as rep

    root = tmp_path / "labelled"
    shutil.copytree(tiny_dataset, root)
    test = (root / "test.txt").read_text().split()
    labels = {n: {"content": "walk", "style": "normal", "mirrored": False, "split": "test"} for n in test}
    (root / "labels.json").write_text(json.dumps(labels))
    vae = str(tiny_model / "vae")
    assert main(["eval-vae", "--data", str(root), "--vae", vae, "--vae", vae, "--out", str(tmp_path / "out")]) == 0
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    a, b = doc["rows"]
    assert a == {**b, "seconds": a["seconds"]}                  # same VAE, same seed: same numbers
    assert a["walking_clips"] == a["locomotion_clips"] == len(test)
    feats = [np.load(root / "new_joint_vecs" / f"{n}.npy") for n in test]
    real = [still_foot_share(rep.features_to_joints(f[: len(f) // 4 * 4].astype(np.float64))) for f in feats]
    assert a["walk_still_real"] == pytest.approx(float(np.mean(real)))
    assert a["pose_error_m"] > 0 and 0 <= a["walk_still_mean"] <= 1 and 0 <= a["slide_mean"] <= 1
    assert a["speed_ratio"] > 0
    assert "| pose error (cm) |" in capsys.readouterr().out
    labels = {n: {**v, "content": "wave-left-hand"} for n, v in labels.items()}
    (root / "labels.json").write_text(json.dumps(labels))
    assert main(["eval-vae", "--data", str(root), "--vae", vae, "--out", str(tmp_path / "out2")]) != 0
    assert "no walking clips" in capsys.readouterr().err
    assert not (tmp_path / "out2" / "results.json").exists()


def test_a_denoiser_trained_through_a_fine_tuned_decoder_records_the_latent_space_it_learns(
        tiny_model, tiny_dataset, tmp_path):
    from salad.models.denoiser import DenoiserConfig
    from salad.models.io import vae_latent_origin
    from salad.training.configs import DenoiserTrainConfig
    from salad.training.denoiser_task import DenoiserTask

    source = tiny_model / "vae"
    tuned = Trainer(VAESANTask(cfg := _san_cfg(tiny_dataset, source, tmp_path / "tuned")), cfg.optim, cfg.run).fit()
    assert vae_latent_origin(tuned) == vae_latent_origin(source) == vae_checksum(source) != vae_checksum(tuned)
    vae, _, _, _ = load_vae(source)
    task = DenoiserTask(DenoiserTrainConfig(
        data=DataConfig(root=str(tiny_dataset), max_frames=40, balance=1.0),
        model=DenoiserConfig(latent_dim=vae.config.latent_dim, dim=32, heads=4, ff_dim=64, layers=1, text_dim=384),
        optim=OptimConfig(batch_size=4, warmup_steps=1, max_steps=1),
        run=RunConfig(out_dir=str(tmp_path / "dn"), bf16=False), vae=str(tuned)), show_progress=False)
    # the source's checksum, which every decoder fine-tuned on its frozen encoder lists: a sibling of `tuned`
    # (another fine-tune of the same source) fits the denoiser as well as `tuned` does
    assert task.vae_checksum == vae_checksum(source)


def test_denoised_latents_pair_training_clips_with_what_the_denoisers_make_and_train_the_decoder(
        tiny_student, tiny_dataset, tmp_path, cli):
    from salad.data.dataset import MotionDataset
    from salad.training.denoised_latents import DenoisedLatents

    out = tmp_path / "denoised.safetensors"
    code, err = cli("data", "denoised-latents", "--model", str(tiny_student), "--data", str(tiny_dataset),
                    "--out", str(out), "--min-frames", "16", "--batch", "3")
    assert code == 0, err
    d = DenoisedLatents(out)
    pipe = load_pipeline(tiny_student)
    ds = MotionDataset(tiny_dataset, "train", max_frames=10 ** 9)
    assert d.names == [it.name for it in ds.items]
    assert set(d.samplers) == {"ddim", "consistency"}
    for k, it in enumerate(ds.items):
        z = d.latent(k)
        assert z.shape == (min(len(it.features), pipe.canvas_frames) // 4, 7, pipe.vae.config.latent_dim)
        assert torch.isfinite(z).all() and z.abs().sum() > 0
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())

    cfg = _san_cfg(tiny_dataset, tiny_student / "vae", tmp_path / "run", lam=0.0)
    cfg.denoised_latents, cfg.denoised_share = str(out), 0.5
    task = VAESANTask(cfg)
    trainer = Trainer(task, task.cfg.optim, task.cfg.run)
    b = task.batch(trainer.rng)
    rows = b["given_rows"]
    assert rows.tolist() == [False, False, True, True] and (b["activation"][rows] == 1).all()
    vae = task.model.vae.eval()
    with torch.no_grad():
        recon, _, _, _ = vae(b["features"], b["activation"], eps=b["eps"], z_given=b["z_given"], given_rows=rows)
        mixed_sampled, _, _, _ = vae(b["features"], b["activation"], eps=b["eps"])
        assert torch.allclose(recon[rows], vae.decode(b["z_given"][rows])[0], atol=1e-5)
        assert torch.allclose(recon[~rows], mixed_sampled[~rows], atol=1e-5)
        # each given window is the clip's own latent at the same place as its features
        w = cfg.data.window // 4
        hits = 0
        for f, z in zip(b["features"][rows], b["z_given"][rows]):
            for k, it in enumerate(ds.items):
                real = torch.from_numpy(ds.normalizer.normalize(it.features))
                lat = d.latent(k)
                for s in range(len(lat) - w + 1):
                    if torch.equal(lat[s:s + w], z):
                        hits += torch.allclose(real[4 * s:4 * s + cfg.data.window], f)
        assert hits == 2
    trainer.fit()
    assert json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[-1])["step"] == 2

    # per-clip weights (data.balance's, which the real windows use too) decide which clips the given half shows
    from salad.training.vae_adv_task import DenoisedWindows
    only = len(task.dataset.items) - 1
    weights = np.zeros(len(task.dataset.items))
    weights[only] = 1.0
    given = DenoisedWindows(str(out), task.dataset, cfg.data.window, task.sources[0], weights)
    real = torch.from_numpy(task.dataset.normalizer.normalize(task.dataset.items[only].features))
    for f in given.batch(6, np.random.default_rng(1))["features"]:
        assert any(torch.allclose(real[s:s + cfg.data.window], f) for s in range(0, len(real) - cfg.data.window + 1, 4))

    # a file made in another latent space is refused
    other, norm, scale, _ = load_vae(tiny_student / "vae")
    with torch.no_grad():
        other.to_dist.weight.add_(0.01)
    save_vae(tmp_path / "other", other, norm, scale)
    cfg.vae = str(tmp_path / "other")
    with pytest.raises(ConfigError, match="another latent space"):
        VAESANTask(cfg)
