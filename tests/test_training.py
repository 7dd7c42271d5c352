import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import denoiser_toml, labelled_copy
import torch.multiprocessing as mp

from salad.models.io import load_vae
from salad.training.configs import DataConfig, OptimConfig, RunConfig, VAETrainConfig
from salad.training.loop import Trainer
from salad.training.vae_task import VAETask
from salad.models.vae import VAEConfig

REPO = Path(__file__).resolve().parents[1]


def vae_config(root, out, steps=6, every=3, bf16=False) -> VAETrainConfig:
    return VAETrainConfig(
        data=DataConfig(root=str(root), window=16, min_frames=16),
        model=VAEConfig(latent_dim=8, dropout=0.0),
        optim=OptimConfig(lr=1e-3, warmup_steps=2, batch_size=4, max_steps=steps),
        run=RunConfig(out_dir=str(out), seed=0, bf16=bf16, checkpoint_every=every, log_every=1))


def fit(cfg):
    task = VAETask(cfg)
    trainer = Trainer(task, cfg.optim, cfg.run)
    trainer.fit()
    return trainer


def test_resume_continues_exactly(tiny_dataset, tmp_path):
    straight = fit(vae_config(tiny_dataset, tmp_path / "a", steps=6))
    fit(vae_config(tiny_dataset, tmp_path / "b", steps=3))
    resumed = fit(vae_config(tiny_dataset, tmp_path / "b", steps=6))
    assert resumed.step_count == 6
    for (k, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.equal(a, b), k
    vae, norm, scale, doc = load_vae(tmp_path / "b" / "model")
    assert doc["meta"]["step"] == 6 and np.isfinite(scale)
    lines = [json.loads(l) for l in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert [l["step"] for l in lines] == list(range(1, 7))


def test_the_log_keeps_the_means_since_its_last_line_and_the_learning_rate_as_it_is(tiny_dataset, tmp_path):
    fit(vae_config(tiny_dataset, tmp_path / "every", steps=4, every=4))
    cfg = vae_config(tiny_dataset, tmp_path / "pairs", steps=4, every=4)
    cfg.run.log_every = 2
    fit(cfg)
    every, pairs = ([json.loads(l) for l in (tmp_path / run / "log.jsonl").read_text().splitlines()]
                    for run in ("every", "pairs"))
    assert [r["step"] for r in pairs] == [2, 4]
    for row, (a, b) in zip(pairs, (every[0:2], every[2:4])):
        assert row["loss"] == pytest.approx((a["loss"] + b["loss"]) / 2, rel=1e-6)
        assert row["lr"] == b["lr"]
    assert every[0]["lr"] < every[1]["lr"], "in the warm-up, so a mean would differ"


class _ExportKilledOnce(VAETask):
    """A VAE task whose process dies while exporting step `at` (the first time only)."""

    def __init__(self, cfg, at):
        super().__init__(cfg)
        self.at, self.exported = at, []

    def export(self, model, path, meta):
        if meta["step"] == self.at and self.at not in self.exported:
            self.exported.append(self.at)
            raise KeyboardInterrupt("killed while exporting")
        self.exported.append(meta["step"])
        super().export(model, path, meta)


def test_a_checkpoint_whose_export_was_killed_is_exported_when_the_run_resumes(tiny_dataset, tmp_path):
    cfg = vae_config(tiny_dataset, tmp_path / "run", steps=6, every=3)
    with pytest.raises(KeyboardInterrupt):
        Trainer(_ExportKilledOnce(cfg, at=6), cfg.optim, cfg.run).fit()
    assert json.loads((tmp_path / "run" / "state" / "config.json").read_text())["meta"]["step"] == 3, \
        "the state is saved after its export, so the run resumes before the step it never exported"
    resumed = _ExportKilledOnce(cfg, at=None)
    Trainer(resumed, cfg.optim, cfg.run).fit()
    assert resumed.exported == [6] and load_vae(tmp_path / "run" / "model")[3]["meta"]["step"] == 6
    steps = [json.loads(l)["step"] for l in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 7))


class _SlowExport(VAETask):
    """A VAE task whose export takes an hour by the trainer's clock (a judged export takes minutes)."""

    def __init__(self, cfg, clock):
        super().__init__(cfg)
        self.clock = clock

    def export(self, model, path, meta):
        super().export(model, path, meta)
        self.clock.offset += 3600.0


def test_the_logged_samples_per_second_leave_out_the_time_spent_exporting(tiny_dataset, tmp_path, monkeypatch):
    import types

    import salad.training.loop as loop
    clock = types.SimpleNamespace(offset=0.0)
    monkeypatch.setattr(loop, "time", types.SimpleNamespace(time=lambda: time.time() + clock.offset))
    cfg = vae_config(tiny_dataset, tmp_path / "run", steps=4, every=2)
    Trainer(_SlowExport(cfg, clock), cfg.optim, cfg.run).fit()
    assert clock.offset == 2 * 3600.0
    rates = [json.loads(l)["samples_per_s"] for l in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    # step 3 follows step 2's export: counted in, its 4 samples would take an hour (0.001 samples/s)
    assert len(rates) == 4 and min(rates) > 0.1, rates


def test_the_validation_log_keeps_one_row_per_step_across_a_resume(tmp_path):
    from salad.eval.selection import log_validation
    for step in (50, 100, 150):
        log_validation(tmp_path, {"step": step, "score": step / 100})
    with open(tmp_path / "val.jsonl", "a") as f:
        f.write('{"step": 200, "sc')                        # a row torn by a kill
    log_validation(tmp_path, {"step": 100, "score": 9.0})  # resumed from step 50, step 100 judged again
    rows = [json.loads(l) for l in (tmp_path / "val.jsonl").read_text().splitlines()]
    assert rows == [{"step": 50, "score": 0.5}, {"step": 100, "score": 9.0}]


def test_resume_refuses_a_different_model(tiny_dataset, tmp_path):
    fit(vae_config(tiny_dataset, tmp_path / "c", steps=2, every=2))
    cfg = vae_config(tiny_dataset, tmp_path / "c", steps=4)
    cfg.model.latent_dim = 16
    with pytest.raises(ValueError, match="different config"):
        fit(cfg)


def _ddp_worker(rank, world, init_file, root, out_file, batch):
    os.environ.update(WORLD_SIZE=str(world), RANK=str(rank), LOCAL_RANK=str(rank))
    torch.distributed.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    torch.set_num_threads(1)
    cfg = vae_config(root, Path(out_file).parent / f"ddp{rank}", steps=1)
    trainer = Trainer(VAETask(cfg), cfg.optim, cfg.run)
    half = {k: v.chunk(world)[rank] for k, v in batch.items()}
    trainer.step(half)
    if rank == 0:
        torch.save  # noqa: B018 - results travel as safetensors, never pickles
        from safetensors.torch import save_file
        save_file({k: v.contiguous() for k, v in trainer.model.state_dict().items()}, out_file)
    torch.distributed.destroy_process_group()


def test_ddp_step_equals_single_process_step_on_combined_batch(tiny_dataset, tmp_path):
    cfg = vae_config(tiny_dataset, tmp_path / "single", steps=1)
    cfg.optim.batch_size = 8
    task = VAETask(cfg)
    batch = task.batch(np.random.default_rng(7))
    single = Trainer(task, cfg.optim, cfg.run)
    single.step(batch)
    out = tmp_path / "ddp.safetensors"
    mp.start_processes(_ddp_worker, args=(2, str(tmp_path / "init"), str(tiny_dataset), str(out), batch),
                       nprocs=2, join=True, start_method="spawn")
    from safetensors.torch import load_file
    ddp = load_file(str(out))
    for k, v in single.model.state_dict().items():
        torch.testing.assert_close(ddp[k], v, atol=1e-6, rtol=1e-5, msg=k)
    # and the step really moved the weights
    fresh = VAETask(cfg).model.state_dict()
    assert any(not torch.equal(fresh[k], v) for k, v in ddp.items())


def test_kill_9_mid_training_loses_at_most_one_interval(tiny_dataset, tmp_path):
    cfg = tmp_path / "vae.toml"
    cfg.write_text(f"""
[data]
root = "{tiny_dataset}"
window = 16
[model]
latent_dim = 8
dropout = 0.0
[optim]
batch_size = 4
warmup_steps = 2
max_steps = 100000
[run]
out_dir = "{tmp_path / 'run'}"
bf16 = false
checkpoint_every = 5
log_every = 1
""")
    cmd = [sys.executable, "-m", "salad.cli", "train", "vae", "--config", str(cfg), "--threads", "1"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = tmp_path / "run" / "state" / "config.json"
    deadline = time.time() + 120
    while time.time() < deadline:
        if state.exists() and json.loads(state.read_text())["meta"]["step"] >= 10:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    log = [json.loads(l) for l in (tmp_path / "run" / "log.jsonl").read_text().splitlines() if l.strip()]
    reached = log[-1]["step"]
    saved = json.loads(state.read_text())["meta"]["step"]
    assert reached - saved < 5 + 1, "at most one checkpoint interval is lost"
    with open(tmp_path / "run" / "log.jsonl", "a") as f:
        f.write('{"step": 99, "lo')                       # a row torn by the kill
    done = subprocess.run(cmd + ["--max-steps", str(saved + 3)], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"resumed {tmp_path / 'run'} at step {saved}" in done.stderr
    _, _, _, doc = load_vae(tmp_path / "run" / "model")
    assert doc["meta"]["step"] == saved + 3
    steps = [json.loads(l)["step"] for l in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert steps == list(range(1, saved + 4)), "one log row per step: the lost ones are forgotten and run again"
    # a kill during a save may leave a half-written temporary folder; the next save clears it
    assert not [p for p in (tmp_path / "run").iterdir() if p.name.startswith(".")], "no temporary leftovers"


@pytest.mark.slow
def test_torchrun_launches_two_process_training(tiny_dataset, tmp_path):
    cfg = tmp_path / "vae.toml"
    cfg.write_text(f"""
[data]
root = "{tiny_dataset}"
window = 16
[model]
latent_dim = 8
[optim]
batch_size = 2
warmup_steps = 1
max_steps = 2
[run]
out_dir = "{tmp_path / 'run'}"
bf16 = false
checkpoint_every = 2
""")
    torchrun = Path(sys.executable).with_name("torchrun")
    out = subprocess.run([str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "salad.cli", "train", "vae",
                          "--config", str(cfg), "--threads", "1"], cwd=REPO, capture_output=True, text=True,
                         timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    _, _, _, doc = load_vae(tmp_path / "run" / "model")
    assert doc["meta"]["step"] == 2 and doc["meta"]["samples_seen"] == 2 * 2 * 2


def test_init_from_an_exported_model_warm_starts(tiny_dataset, tmp_path):
    fit(vae_config(tiny_dataset, tmp_path / "first", steps=3))
    cfg = vae_config(tiny_dataset, tmp_path / "second", steps=1)
    task = VAETask(cfg)
    trainer = Trainer(task, cfg.optim, cfg.run)
    trainer.init_weights(tmp_path / "first" / "model")
    vae, _, _, _ = load_vae(tmp_path / "first" / "model")
    for k, v in vae.state_dict().items():
        assert torch.equal(trainer.model.vae.state_dict()[k], v), k
    assert trainer.step_count == 0


def test_continuing_refuses_a_snapshot_that_is_already_as_far(tiny_dataset, tmp_path):
    fit(vae_config(tiny_dataset, tmp_path / "first", steps=3))
    cfg = vae_config(tiny_dataset, tmp_path / "second", steps=3)
    trainer = Trainer(VAETask(cfg), cfg.optim, cfg.run)
    with pytest.raises(ValueError, match="trained for 3 steps already"):
        trainer.init_weights(tmp_path / "first" / "model", carry_step=True)


def test_denoiser_continues_a_snapshot_from_its_step_with_a_rewarm(tiny_model, tiny_dataset, tmp_path):
    from salad.cli import main
    from salad.models.io import load_denoiser

    _, before = load_denoiser(tiny_model / "denoiser")
    start = before["meta"]["step"]
    cfg = denoiser_toml(tmp_path / "d.toml", tiny_dataset, steps=start + 3)
    out = tmp_path / "more"
    assert main(["train", "denoiser", "--config", str(cfg), "--out-dir", str(out), "--vae", str(tiny_model / "vae"),
                 "--continue-from", str(tiny_model / "denoiser")]) == 0
    _, after = load_denoiser(out / "model")
    assert after["meta"]["step"] == start + 3
    assert after["meta"]["samples_seen"] == before["meta"]["samples_seen"] + 3 * 4
    rows = [json.loads(l) for l in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [start + 1, start + 2, start + 3]
    # a fresh optimiser warms up again from the snapshot's step: 1/4, 2/4, 3/4 of lr
    assert [r["lr"] for r in rows] == pytest.approx([2.5e-4, 5e-4, 7.5e-4])
    # resuming the continued run keeps the re-warm-up where it was
    denoiser_toml(cfg, tiny_dataset, steps=start + 5)
    assert main(["train", "denoiser", "--config", str(cfg), "--out-dir", str(out), "--vae", str(tiny_model / "vae"),
                 "--continue-from", str(tiny_model / "denoiser")]) == 0
    rows = [json.loads(l) for l in (out / "log.jsonl").read_text().splitlines()]
    assert [r["lr"] for r in rows[3:]] == pytest.approx([1e-3, 1e-3])


def test_denoiser_init_from_refuses_another_vaes_latents(tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    fit(vae_config(tiny_dataset, tmp_path / "other-vae", steps=1, every=1))
    cfg = denoiser_toml(tmp_path / "d.toml", tiny_dataset, steps=100)
    assert main(["train", "denoiser", "--config", str(cfg), "--out-dir", str(tmp_path / "x"),
                 "--vae", str(tmp_path / "other-vae" / "model"), "--init-from", str(tiny_model / "denoiser")]) == 2
    assert "another VAE" in capsys.readouterr().err
    assert not (tmp_path / "x" / "model").exists()
    # asked for, the old denoiser is the start of one for the new latents, and the export names its new partner
    from salad.models.io import load_denoiser, vae_checksum
    cfg = denoiser_toml(tmp_path / "d.toml", tiny_dataset, steps=2)
    assert main(["train", "denoiser", "--config", str(cfg), "--out-dir", str(tmp_path / "y"),
                 "--vae", str(tmp_path / "other-vae" / "model"), "--init-from", str(tiny_model / "denoiser"),
                 "--new-latents"]) == 0
    _, doc = load_denoiser(tmp_path / "y" / "model")
    assert doc["config"]["vae_checksum"] == vae_checksum(tmp_path / "other-vae" / "model")
    assert main(["train", "vae", "--config", str(cfg), "--new-latents"]) == 2
    assert "--new-latents applies to a denoiser" in capsys.readouterr().err


def test_vae_override_only_applies_where_there_is_a_vae(tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    cfg = tmp_path / "v.toml"
    cfg.write_text(f'[data]\nroot = "{tiny_dataset}"\n')
    assert main(["train", "vae", "--config", str(cfg), "--vae", "x"]) == 2
    assert "--vae does not apply to a VAETrainConfig" in capsys.readouterr().err


def test_balance_override_is_checked_and_kept_from_trainers_that_mean_otherwise(tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    cfg = tmp_path / "v.toml"
    cfg.write_text(f'[data]\nroot = "{tiny_dataset}"\n')
    assert main(["train", "vae", "--config", str(cfg), "--balance", "-2"]) == 2
    assert "data.balance must be in [-1, 1], got -2.0" in capsys.readouterr().err
    assert main(["train", "classifier", "--config", str(cfg), "--balance", "0.5"]) == 2
    assert "--balance applies to the vae, vae-san, the denoiser and consistency" in capsys.readouterr().err


def test_devices_are_resolved_or_refused_clearly(monkeypatch):
    from salad.precision import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu") == resolve_device(None) == resolve_device(" CPU ")
    for name, why in (("cuda", "sees no CUDA GPU"), ("cuda:1", "sees no CUDA GPU"), ("tpu", "unknown device"),
                      ("mps", "not supported")):
        with pytest.raises(ValueError, match=why):
            resolve_device(name)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == torch.device("cuda")
    with pytest.raises(ValueError, match="has 1 CUDA GPU"):
        resolve_device("cuda:1")


def test_training_asked_for_a_gpu_on_a_machine_without_one_stops_before_any_step(tiny_dataset, tmp_path,
                                                                                capsys, monkeypatch):
    from salad.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = tmp_path / "v.toml"
    cfg.write_text(f'[data]\nroot = "{tiny_dataset}"\nwindow = 16\n[optim]\nbatch_size = 4\nmax_steps = 2\n')
    assert main(["train", "vae", "--config", str(cfg), "--out-dir", str(tmp_path / "gpu"), "--device", "cuda"]) == 2
    assert "sees no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "gpu").exists()
    trainer = Trainer(VAETask(vae_config(tiny_dataset, tmp_path / "cpu", steps=1)), OptimConfig(max_steps=1),
                      RunConfig(out_dir=str(tmp_path / "cpu"), device="cpu"))
    assert trainer.device == torch.device("cpu") and next(trainer.model.parameters()).device.type == "cpu"


def test_denoiser_batches_are_the_same_whether_posteriors_are_cached_or_not(tiny_model, tiny_dataset, tmp_path):
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.denoiser import DenoiserConfig
    from salad.training.configs import DenoiserTrainConfig
    from salad.training.denoiser_task import DenoiserTask

    cfg = DenoiserTrainConfig(
        data=DataConfig(root=str(tiny_dataset), max_frames=80),      # the 72-frame motions fit this canvas
        model=DenoiserConfig(latent_dim=8, dim=32, heads=4, ff_dim=64, layers=3, text_dim=384),
        diffusion=DiffusionConfig(), optim=OptimConfig(batch_size=4),
        run=RunConfig(out_dir=str(tmp_path / "run")), vae=str(tiny_model / "vae"))
    warm, cold = DenoiserTask(cfg, show_progress=False), DenoiserTask(cfg, show_progress=False)
    for auto in (0.0, 1.0):
        cfg.auto_length_prob = auto
        for _ in range(5):
            warm.batch(np.random.default_rng(7))
        assert warm._posteriors
        torch.manual_seed(3)
        a = warm.batch(np.random.default_rng(1))
        torch.manual_seed(3)
        b = cold.batch(np.random.default_rng(1))
        assert torch.allclose(a["latents"], b["latents"], atol=1e-5)
        cold._posteriors.clear()
    i, (mu, logvar) = next(iter(warm._posteriors.items()))
    f = warm.dataset.items[i].features
    fresh, _ = warm.vae.encode(*warm._canvas([warm.normalizer.normalize(f[: len(f) // 4 * 4])]))
    assert mu.shape == fresh[0].shape and torch.allclose(mu, fresh[0], atol=1e-5)


def test_bf16_runs_train_in_fp32_on_a_cpu_without_native_bf16(tiny_dataset, tmp_path, monkeypatch, capsys):
    import salad.training.loop as loop

    monkeypatch.setattr(loop, "bf16_supported", lambda device: False)
    cfg = vae_config(tiny_dataset, tmp_path / "run", steps=1, bf16=True)
    trainer = Trainer(VAETask(cfg), cfg.optim, cfg.run)
    assert not trainer.bf16 and "no native bf16" in capsys.readouterr().err
    with trainer.autocast():
        assert not torch.is_autocast_enabled("cpu")
    monkeypatch.setattr(loop, "bf16_supported", lambda device: True)
    trainer = Trainer(VAETask(cfg), cfg.optim, cfg.run)
    with trainer.autocast():
        assert torch.is_autocast_enabled("cpu")


def _balance_config(root, tiny_model, out, balance):
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.denoiser import DenoiserConfig
    from salad.training.configs import DenoiserTrainConfig

    return DenoiserTrainConfig(
        data=DataConfig(root=str(root), max_frames=40, balance=balance),
        model=DenoiserConfig(latent_dim=8, dim=32, heads=4, ff_dim=64, layers=3, text_dim=384),
        diffusion=DiffusionConfig(), optim=OptimConfig(batch_size=4, warmup_steps=2, max_steps=2),
        run=RunConfig(out_dir=str(out), bf16=False, checkpoint_every=2), vae=str(tiny_model / "vae"),
        text_dropout=0.0)


@pytest.mark.parametrize("balance", [1.0, 0.5, 0.0, -0.5])
def test_class_balance_draws_rare_actions_as_configured(tiny_model, tiny_dataset, tmp_path, balance):
    from salad.training.denoiser_task import DenoiserTask

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)         # 2 kicks, 6 walks in train
    task = DenoiserTask(_balance_config(root, tiny_model, tmp_path / "run", balance), show_progress=False)
    drawn = []
    bank_batch = task.text.batch
    task.text.batch = lambda captions, multiple=1: (drawn.extend(captions), bank_batch(captions, multiple))[1]
    rng = np.random.default_rng(0)
    for auto in (0.0, 1.0):
        task.cfg.auto_length_prob = auto
        for _ in range(150):
            task.batch(rng)
    share = sum(c == "a person kicks" for c in drawn) / len(drawn)
    expected = 2 ** balance / (2 ** balance + 6 ** balance)       # 0.25, 0.37, 0.5, 0.63
    assert abs(share - expected) < 0.05, (share, expected)


def test_an_anchor_holds_common_actions_while_rare_ones_learn_from_the_data(tiny_model, tiny_dataset, tmp_path):
    from salad.config import ConfigError
    from salad.training.denoiser_task import DenoiserTask, DenoiserTraining

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)         # 2 kicks, 6 walks in train

    def task_for(out, anchor="", max_clips=2):
        cfg = _balance_config(root, tiny_model, tmp_path / out, 0.0)
        cfg.anchor, cfg.anchor_max_clips = anchor, max_clips
        cfg.optim.max_steps, cfg.optim.lr = 30, 3e-3
        return DenoiserTask(cfg, show_progress=False)

    anchored = task_for("anchored", str(tiny_model / "denoiser"))
    drawn = []
    bank_batch = anchored.text.batch
    anchored.text.batch = lambda captions, multiple=1: (drawn.extend(captions), bank_batch(captions, multiple))[1]
    batch = anchored.batch(np.random.default_rng(1))
    assert batch["learn"].tolist() == [c == "a person kicks" for c in drawn]
    # from the anchor's own weights, without dropout, the held rows are already at their target
    anchored.load_weights(anchored.model, tiny_model / "denoiser")
    anchored.model.eval()
    batch["learn"][:] = False
    loss, logs = anchored.loss(anchored.model, batch)
    assert float(loss.detach()) < 1e-8 and logs["learn"] == 0.0
    batch["learn"][:] = True
    assert float(anchored.loss(anchored.model, batch)[0].detach()) > 1e-3     # the data's target is not the anchor's

    # trained on from the anchor's weights, the walks stay near the anchor's; without it they drift
    probe = anchored.batch(np.random.default_rng(7))
    walks = ~probe.pop("learn")
    assert walks.any()
    with torch.no_grad():
        _, _, start = DenoiserTraining(anchored.anchor, anchored.schedule)(probe)
    drift = {}
    for name, task in (("anchored", anchored), ("free", task_for("free"))):
        trainer = Trainer(task, task.cfg.optim, task.cfg.run)
        trainer.init_weights(tiny_model / "denoiser")
        trainer.fit()
        with torch.no_grad():
            _, _, x0 = trainer.model.eval()(probe)
        drift[name] = float((x0 - start)[walks].pow(2).mean())
    assert drift["anchored"] < 0.5 * drift["free"], drift

    for clips in (1, 6):                                            # every class rare / none rare
        with pytest.raises(ConfigError, match="anchor_max_clips"):
            task_for(f"bad{clips}", str(tiny_model / "denoiser"), clips)


@pytest.mark.parametrize("balance", [1.0, 0.0])
def test_vae_windows_follow_class_balance_and_length(tiny_dataset, tmp_path, balance):
    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)         # 2 kicks, 6 walks in train
    cfg = vae_config(root, tmp_path / "run")
    cfg.data.balance = balance
    task = VAETask(cfg)
    lengths = np.array([len(it.features) for it in task.dataset.items], dtype=np.float64)
    kick = np.array([it.captions == ["a person kicks"] for it in task.dataset.items])
    assert kick.sum() == 2 and len(kick) == 8
    share = task.sampler.weights[kick].sum()
    if balance == 1.0:      # as recorded: every frame alike
        expected = lengths[kick].sum() / lengths.sum()
    else:                   # each class alike; within a class, by length
        expected = 0.5
        assert task.sampler.weights[~kick].sum() == pytest.approx(0.5)
        assert np.allclose(task.sampler.weights[kick] / share, lengths[kick] / lengths[kick].sum())
    assert share == pytest.approx(expected)
    rng = np.random.default_rng(0)
    drawn = rng.choice(len(kick), size=4000, p=task.sampler.weights)
    assert abs(kick[drawn].mean() - expected) < 0.03


def test_class_balance_needs_labels_and_a_valid_exponent(tiny_model, tiny_dataset, tmp_path):
    from salad.config import ConfigError
    from salad.training.denoiser_task import DenoiserTask

    with pytest.raises(ConfigError, match="labels"):
        DenoiserTask(_balance_config(tiny_dataset, tiny_model, tmp_path / "a", 0.5), show_progress=False)
    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)
    for bad in (1.5, -1.5):
        with pytest.raises(ConfigError, match=r"data.balance must be in \[-1, 1\]"):
            DenoiserTask(_balance_config(root, tiny_model, tmp_path / "b", bad), show_progress=False)
        vae = vae_config(root, tmp_path / "v")             # the VAE draws its windows by the same rule
        vae.data.balance = bad
        with pytest.raises(ConfigError, match=r"data.balance must be in \[-1, 1\]"):
            VAETask(vae)


def test_a_run_saved_before_a_config_field_existed_resumes_at_its_default(tiny_model, tiny_dataset, tmp_path):
    from salad.training.denoiser_task import DenoiserTask

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)
    cfg = _balance_config(root, tiny_model, tmp_path / "run", 1.0)
    Trainer(DenoiserTask(cfg, show_progress=False), cfg.optim, cfg.run).fit()
    saved = tmp_path / "run" / "state" / "config.json"
    doc = json.loads(saved.read_text())
    del doc["config"]["data"]["balance"]                            # as written before the field existed
    saved.write_text(json.dumps(doc))
    cfg.optim.max_steps = 3
    resumed = Trainer(DenoiserTask(cfg, show_progress=False), cfg.optim, cfg.run)
    resumed.fit()
    assert resumed.step_count == 3
    cfg.data.balance, cfg.optim.max_steps = 0.5, 4                  # a changed recipe is still refused
    with pytest.raises(ValueError, match=r"different config \(differs in \['data'\]: data.balance is 0.5 here, "
                                         r"1.0 in the run\)"):
        Trainer(DenoiserTask(cfg, show_progress=False), cfg.optim, cfg.run).fit()


def test_the_denoisers_contact_loss_holds_decoded_feet_to_the_real_ones(tiny_model, tiny_dataset, tmp_path):
    from salad.config import ConfigError
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.denoiser import DenoiserConfig
    from salad.training.configs import DenoiserTrainConfig
    from salad.training.denoiser_task import DenoiserTask

    def config(weight, auto):
        return DenoiserTrainConfig(
            data=DataConfig(root=str(tiny_dataset), max_frames=80), contact_loss=weight, auto_length_prob=auto,
            model=DenoiserConfig(latent_dim=8, dim=32, heads=4, ff_dim=64, layers=3, text_dim=384),
            diffusion=DiffusionConfig(), optim=OptimConfig(batch_size=4, warmup_steps=1, max_steps=1),
            run=RunConfig(out_dir=str(tmp_path / f"run{weight}{auto}"), bf16=False))

    for auto in (0.0, 1.0):
        cfg = config(0.5, auto)
        cfg.vae = str(tiny_model / "vae")
        task = DenoiserTask(cfg, show_progress=False)
        trainer = Trainer(task, cfg.optim, cfg.run)
        batch = task.batch(np.random.default_rng(0))
        # the real motions ride along, normalised, frame for frame with the latents
        assert batch["features"].shape[:2] == batch["valid"].shape == (4, 4 * batch["latents"].shape[1])
        real_contacts = task.normalizer.denormalize(batch["features"])[..., 259:263]
        assert ((real_contacts > 0.5) & batch["valid"][..., None]).any()
        loss, logs = task.loss(task.model, batch)
        assert logs["foot"] > 0 and float(loss.detach()) == pytest.approx(logs["loss"] + 0.5 * logs["foot"], rel=1e-4)
        # the term reaches the denoiser through the decoder, and the frozen VAE learns nothing
        _, _, x0 = task.model(batch)
        task.foot_error(x0, batch).backward()
        assert all(p.grad is None for p in task.vae.parameters())
        assert sum(float(p.grad.abs().sum()) for p in task.model.parameters() if p.grad is not None) > 0
        task.model.zero_grad(set_to_none=True)
        trainer.step(batch)
    cfg = config(-1.0, 0.0)
    cfg.vae = str(tiny_model / "vae")
    with pytest.raises(ConfigError, match="contact_loss"):
        DenoiserTask(cfg, show_progress=False)


def test_posterior_noise_zero_trains_on_the_vaes_posterior_means(tiny_model, tiny_dataset, tmp_path):
    from salad.config import ConfigError
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.denoiser import DenoiserConfig
    from salad.training.configs import DenoiserTrainConfig
    from salad.training.denoiser_task import DenoiserTask

    def latents(noise, seed):
        cfg = DenoiserTrainConfig(
            data=DataConfig(root=str(tiny_dataset), max_frames=80), auto_length_prob=1.0, posterior_noise=noise,
            model=DenoiserConfig(latent_dim=8, dim=32, heads=4, ff_dim=64, layers=3, text_dim=384),
            diffusion=DiffusionConfig(), optim=OptimConfig(batch_size=4, warmup_steps=1, max_steps=1),
            run=RunConfig(out_dir=str(tmp_path / "run"), bf16=False), vae=str(tiny_model / "vae"))
        task = DenoiserTask(cfg, show_progress=False)
        torch.manual_seed(seed)
        batch = task.batch(np.random.default_rng(0))
        return batch, task

    (a, task), (b, _) = latents(0.0, 1), latents(0.0, 2)
    # the same clips give the same latents whatever the torch seed: the scaled posterior means
    torch.testing.assert_close(a["latents"], b["latents"])
    means = torch.stack([mu for mu, _ in task._posteriors.values()])     # clips that fit are encoded once
    matched = sum(any(torch.allclose(row, m * task.latent_scale) for m in means) for row in a["latents"])
    assert matched >= len(means) >= 1
    (c, _), (d, _) = latents(1.0, 1), latents(1.0, 2)
    assert float((c["latents"] - d["latents"]).abs().max()) > 1e-3      # posterior samples differ
    with pytest.raises(ConfigError, match="posterior_noise"):
        latents(-0.5, 0)


def _bundle_config(tiny_dataset, tiny_model, out, max_frames=80, bundle=""):
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.denoiser import DenoiserConfig
    from salad.training.configs import DenoiserTrainConfig

    return DenoiserTrainConfig(
        data=DataConfig(root=str(tiny_dataset), max_frames=max_frames, bundle=bundle), posterior_noise=0.0,
        model=DenoiserConfig(latent_dim=8, dim=32, heads=4, ff_dim=64, layers=3, text_dim=384),
        diffusion=DiffusionConfig(), optim=OptimConfig(batch_size=4, warmup_steps=1, max_steps=2),
        run=RunConfig(out_dir=str(out), bf16=False, checkpoint_every=2), vae=str(tiny_model / "vae"))


def test_fixed_length_batches_come_in_a_few_masked_shapes(tiny_model, tiny_dataset, tmp_path):
    from salad.training.denoiser_task import FRAME_BUCKET, TOKEN_BUCKET, DenoiserTask

    cfg = _bundle_config(tiny_dataset, tiny_model, tmp_path / "a")
    cfg.auto_length_prob = 0.0
    task = DenoiserTask(cfg, show_progress=False)
    rng = np.random.default_rng(3)
    for _ in range(12):
        b = task.batch(rng)
        frames, tokens = 4 * b["latents"].shape[1], b["text"].shape[1]
        assert frames % FRAME_BUCKET == 0 or frames == task.canvas
        assert tokens % TOKEN_BUCKET == 0
        # the padding is masked, and no bucket is wider than the longest row needs
        used = b["frame_mask"].sum(1)
        assert 4 * int(used.max()) > frames - FRAME_BUCKET
        assert int(torch.count_nonzero(b["latents"][~b["frame_mask"]])) == 0
        words = b["text_mask"].sum(1)
        assert tokens - TOKEN_BUCKET < int(words.max()) <= tokens
        assert int(torch.count_nonzero(b["text"][~b["text_mask"]])) == 0


def test_a_latent_bundle_trains_on_the_batches_the_dataset_gives(tiny_model, tiny_dataset, tmp_path):
    from salad.training.denoiser_task import DenoiserTask
    from salad.training.latent_bundle import write_bundle

    source = DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "a"), show_progress=False)
    part = 8 * 1024
    assert source.text.pooled.numel() * 4 > 2 * part       # the sentence features too span several parts
    out = write_bundle(source, tmp_path / "bundle", part_bytes=part, progress=False)
    files = sorted(out.glob("part-*.safetensors"))
    assert len(files) > 1 and all(f.stat().st_size <= part for f in files)
    cfg = _bundle_config(tiny_dataset, tiny_model, tmp_path / "b", bundle=str(out))
    cfg.data.root = str(tmp_path / "nowhere")                    # nothing is read from the dataset
    bundled = DenoiserTask(cfg, show_progress=False)
    for auto in (0.0, 1.0):
        source.cfg.auto_length_prob = bundled.cfg.auto_length_prob = auto
        a, b = source.batch(np.random.default_rng(5)), bundled.batch(np.random.default_rng(5))
        assert a["latents"].shape == b["latents"].shape
        assert torch.allclose(a["latents"], b["latents"], atol=2e-2, rtol=1e-2)        # fp16 storage
        assert (a["frame_mask"] is None) == (b["frame_mask"] is None)
        if a["frame_mask"] is not None:
            assert torch.equal(a["frame_mask"], b["frame_mask"])
        assert torch.equal(a["text"], b["text"]) and torch.equal(a["pooled"], b["pooled"])
        assert torch.equal(a["noise"], b["noise"]) and torch.equal(a["timesteps"], b["timesteps"])
    Trainer(bundled, cfg.optim, cfg.run, ema_decay=cfg.ema_decay).fit()
    doc = json.loads((tmp_path / "b" / "model" / "config.json").read_text())
    assert doc["config"]["text_encoder"] == source.text_spec


def test_a_tower_bundle_computes_the_captions_features_where_it_is_read(tiny_model, tiny_dataset, tmp_path):
    from salad.training.denoiser_task import DenoiserTask
    from salad.training.latent_bundle import LatentBundle, write_bundle

    source = DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "a"), show_progress=False)
    lean = DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "a"), show_progress=False,
                        encode_text=False)
    assert lean.text is None
    out = write_bundle(lean, tmp_path / "bundle", part_bytes=8 << 20, progress=False, text="tower")
    bundle = LatentBundle(out)
    assert bundle.text.captions == source.text.captions
    assert torch.equal(bundle.text.lengths, source.text.lengths)
    want, got = source.text.flat.float(), bundle.text.flat.float()
    # fp16 weights computed in fp32, then stored in bf16 like the encoder's own: rounding, not another model
    assert float((got - want).norm() / want.norm()) < 2e-2
    assert float((bundle.text.pooled - source.text.pooled).abs().max()) < 2e-2
    cfg = _bundle_config(tiny_dataset, tiny_model, tmp_path / "b", bundle=str(out))
    Trainer(DenoiserTask(cfg, show_progress=False), cfg.optim, cfg.run, ema_decay=cfg.ema_decay).fit()
    assert (tmp_path / "b" / "model" / "config.json").is_file()
    with pytest.raises(ValueError, match="text must be one of"):
        write_bundle(lean, tmp_path / "other", part_bytes=8 << 20, progress=False, text="ids")


def test_a_bundle_keeps_windows_of_motions_longer_than_the_canvas(tiny_model, tiny_dataset, tmp_path):
    from salad.training.denoiser_task import DenoiserTask
    from salad.training.latent_bundle import LatentBundle, write_bundle

    source = DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "a", max_frames=40), show_progress=False)
    bundle = LatentBundle(write_bundle(source, tmp_path / "bundle", part_bytes=1 << 20, windows=3, progress=False))
    long = [i for i, n in enumerate(bundle.lengths) if n > 40]
    assert long and (bundle.window_of[long] >= 0).all()
    i = long[0]
    f = source.dataset.items[i].features
    last, _ = source.vae.encode(*source._canvas([source.normalizer.normalize(f[len(f) - 40:])]))
    assert torch.allclose(bundle.windows[bundle.window_of[i], -1], last[0], atol=1e-2)
    drawn = {int(torch.argmin((bundle.windows[bundle.window_of[i]] - bundle.rows([i], np.random.default_rng(s))[0])
                              .abs().flatten(1).amax(1))) for s in range(20)}
    assert len(drawn) > 1                                        # a window drawn at random


def test_a_bundle_refuses_what_it_cannot_give_and_parts_that_changed(tiny_model, tiny_dataset, tmp_path):
    from salad.checkpoint import CheckpointError
    from salad.config import ConfigError
    from salad.training.denoiser_task import DenoiserTask
    from salad.training.latent_bundle import write_bundle

    source = DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "a"), show_progress=False)
    out = write_bundle(source, tmp_path / "bundle", part_bytes=1 << 20, progress=False)
    cfg = _bundle_config(tiny_dataset, tiny_model, tmp_path / "b", bundle=str(out))
    cfg.posterior_noise = 1.0
    with pytest.raises(ConfigError, match="posterior_noise = 0"):
        DenoiserTask(cfg, show_progress=False)
    with pytest.raises(ConfigError, match="canvas"):
        DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "c", max_frames=40, bundle=str(out)),
                     show_progress=False)
    part = next(out.glob("part-*.safetensors"))
    data = bytearray(part.read_bytes())
    data[-3] ^= 0xFF
    part.write_bytes(bytes(data))
    with pytest.raises(CheckpointError):
        DenoiserTask(_bundle_config(tiny_dataset, tiny_model, tmp_path / "d", bundle=str(out)), show_progress=False)


def test_the_cli_bundles_a_config_and_trains_from_the_bundle(tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    cfg = denoiser_toml(tmp_path / "d.toml", tiny_dataset, steps=2)
    cfg.write_text("posterior_noise = 0.0\n" + cfg.read_text())
    vae = str(tiny_model / "vae")
    assert main(["data", "bundle", "--config", str(cfg), "--vae", vae, "--out", str(tmp_path / "b"),
                 "--part-mib", "0"]) == 2
    assert "--part-mib must be > 0" in capsys.readouterr().err
    assert main(["data", "bundle", "--config", str(cfg), "--vae", vae, "--out", str(tmp_path / "b"),
                 "--part-mib", "0.05"]) == 0
    assert "parts, the largest" in capsys.readouterr().out
    assert all(f.stat().st_size <= 0.05 * 2 ** 20 for f in (tmp_path / "b").glob("*.safetensors"))
    assert main(["train", "denoiser", "--config", str(cfg), "--vae", vae, "--bundle", str(tmp_path / "b"),
                 "--data", str(tmp_path / "nowhere"), "--out-dir", str(tmp_path / "run")]) == 0
    doc = json.loads((tmp_path / "run" / "model" / "config.json").read_text())
    assert doc["meta"]["train_config"]["data"]["bundle"] == str(tmp_path / "b")


def test_min_snr_weighting_rescales_each_timesteps_loss_and_caps_it(tiny_model, tiny_dataset, tmp_path):
    from salad.config import ConfigError
    from salad.training.denoiser_task import DenoiserTask

    cfg = _bundle_config(tiny_dataset, tiny_model, tmp_path / "a")
    cfg.min_snr_gamma = 5.0
    task = DenoiserTask(cfg, show_progress=False)
    model = task.model.eval()                                   # no dropout: the two losses see one forward
    t = torch.tensor([0, 100, 400, 999])
    a = task.schedule.alphas_cumprod[t].float()
    snr = a / (1 - a)
    torch.testing.assert_close(model.snr_weights(t), torch.minimum(snr, torch.tensor(5.0)) / (snr + 1))
    assert model.snr_weights(t)[0] < 0.05 and model.snr_weights(t)[-1] < 0.01    # capped clean end, noisy end
    batch = task.batch(np.random.default_rng(0))
    for step in (0, 400):
        batch["timesteps"] = torch.full_like(batch["timesteps"], step)
        with torch.no_grad():
            weighted = model(batch)[0]
            model.min_snr_gamma = 0.0
            plain = model(batch)[0]
            model.min_snr_gamma = 5.0
        torch.testing.assert_close(weighted, plain * model.snr_weights(torch.tensor([step]))[0])
    cfg.min_snr_gamma = -1.0
    with pytest.raises(ConfigError, match="min_snr_gamma"):
        DenoiserTask(cfg, show_progress=False)


def test_the_denoisers_validation_loss_is_logged_and_compares_across_recipes(tiny_model, tiny_dataset, tmp_path):
    from salad.data.dataset import MotionDataset
    from salad.training.denoiser_task import DenoiserTask

    cfg = _bundle_config(tiny_dataset, tiny_model, tmp_path / "a")
    cfg.run.validate_every, cfg.run.log_every, cfg.optim.max_steps = 2, 3, 4
    cfg.min_snr_gamma = 5.0
    task = DenoiserTask(cfg, show_progress=False)
    trainer = Trainer(task, cfg.optim, cfg.run, ema_decay=cfg.ema_decay)
    trainer.fit()
    rows = [json.loads(l) for l in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    # one row per logged or validated step; the validated ones carry the loss
    assert [r["step"] for r in rows] == [2, 3, 4]
    assert [("val_loss" in r) for r in rows] == [True, False, True]
    assert all(np.isfinite(r["val_loss"]) and r["val_loss"] > 0 for r in rows if "val_loss" in r)
    # every validation motion once, at its own length, the same draws at every call
    val = MotionDataset(tiny_dataset, "val", max_frames=80, normalizer=task.normalizer)
    masks = torch.cat([b["frame_mask"].sum(1) for b in task._validation])
    assert sorted((4 * masks).tolist()) == sorted(min(len(it.features), task.canvas) // 4 * 4 for it in val.items)
    model = trainer.ema
    assert trainer.validate() == trainer.validate() == pytest.approx(rows[-1]["val_loss"])
    # unweighted by min-SNR, so runs with and without it read on one scale
    model.min_snr_gamma = 0.0
    assert trainer.validate() == pytest.approx(rows[-1]["val_loss"])
    # the model in training mode (dropout) comes back in training mode
    trainer.model.train()
    trainer.validate()
    assert trainer.model.training and not trainer.ema.training
    # a run in bf16 validates in fp32, on the scale of a run in fp32
    cfg.run.bf16 = True
    bf16_run = Trainer(task, cfg.optim, cfg.run, ema_decay=cfg.ema_decay)
    bf16_run.ema.load_state_dict(model.state_dict())
    assert bf16_run.validate() == trainer.validate()


def test_the_cli_prints_a_snapshots_validation_loss_without_training(tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    cfg = denoiser_toml(tmp_path / "d.toml", tiny_dataset, steps=2)
    args = ["train", "denoiser", "--config", str(cfg), "--vae", str(tiny_model / "vae"),
            "--out-dir", str(tmp_path / "run")]
    assert main(args + ["--init-from", str(tiny_model / "denoiser"), "--validate-only"]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert first["val_loss"] > 0 and not (tmp_path / "run").exists()
    assert main(args + ["--init-from", str(tiny_model / "denoiser"), "--validate-only"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == first
    # a bundle holds no validation split: the loss is read from data.root all the same
    assert main(args + ["--init-from", str(tiny_model / "denoiser"), "--validate-only",
                        "--bundle", str(tmp_path / "no-bundle")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == first
    assert main(args + ["--validate-only"]) == 2
    assert "--validate-only applies to a denoiser given with --init-from" in capsys.readouterr().err
