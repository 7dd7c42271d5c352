"""The consistency-distilled student: its sampler, its distillation and the pipeline paths
that run it (generate, edit, control, real-motion edits)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from salad.diffusion.consistency import consistency_fn, consistency_sample, grid_timesteps
from conftest import consistency_toml, denoiser_toml, labelled_copy
from salad.diffusion.schedule import DiffusionConfig, NoiseSchedule


def _oracle(schedule: NoiseSchedule, x0: torch.Tensor):
    """A v-prediction model that knows the clean latent: its x0 estimate is x0 at every timestep."""
    a = schedule.alphas_cumprod

    def fn(x, t):
        at = a[t].view(-1, *([1] * (x.ndim - 1))).to(x.dtype)
        eps = (x - at.sqrt() * x0) / (1 - at).sqrt()
        return at.sqrt() * eps - (1 - at).sqrt() * x0
    return fn


def test_grid_is_the_teachers_50_step_ddim_grid():
    s = NoiseSchedule(DiffusionConfig())
    grid = grid_timesteps(s)
    assert grid[0] == 19 and grid[-1] == 999 and len(grid) == 50
    assert set(int(t) for t in s.sampler("consistency", 4).timesteps) <= set(grid.tolist())


def test_consistency_function_is_the_identity_at_the_boundary():
    s = NoiseSchedule(DiffusionConfig())
    z = torch.randn(3, 4, 7, 8)
    out = torch.randn_like(z)
    assert torch.allclose(consistency_fn(s, z, out, torch.zeros(3, dtype=torch.long)), z)
    # and the x0 estimate itself far from it
    t = torch.full((3,), 999)
    x0, _ = s.to_x0_eps(z, out, t)
    assert torch.allclose(consistency_fn(s, z, out, t), x0, atol=1e-4)


@pytest.mark.parametrize("steps", [1, 2, 4])
def test_consistency_sampling_returns_the_oracles_clean_latent(steps):
    s = NoiseSchedule(DiffusionConfig())
    x0 = torch.randn(2, 6, 7, 8)
    seen = []
    out = consistency_sample(_oracle(s, x0), torch.randn_like(x0), s, steps, generator=torch.Generator().manual_seed(0),
                             on_step=lambda i, n, x: seen.append((i, n)))
    assert torch.allclose(out, x0, atol=1e-3)
    assert seen == [(i + 1, steps) for i in range(steps)]


def test_shared_noise_renoises_every_row_alike():
    s = NoiseSchedule(DiffusionConfig())
    rows = []

    def model(x, t):
        rows.append(x.clone())
        return torch.zeros_like(x)
    noise = torch.randn(1, 6, 7, 8).repeat(2, 1, 1, 1)
    consistency_sample(model, noise, s, 3, generator=torch.Generator().manual_seed(1), shared_noise=True)
    assert all(torch.equal(x[0], x[1]) for x in rows)


def test_consistency_sampler_steps_are_bounded_by_the_grid():
    s = NoiseSchedule(DiffusionConfig())
    assert [int(t) for t in s.sampler("consistency", 4).timesteps] == [999, 759, 499, 259]
    with pytest.raises(ValueError, match="1..50"):
        s.sampler("consistency", 51)


# ---------------------------------------------------------------- distillation

def test_a_fresh_student_is_its_teacher_without_guidance(tiny_model):
    from salad.models.io import load_denoiser
    from salad.training.consistency_task import ConsistencyTraining

    teacher, _ = load_denoiser(tiny_model / "denoiser")
    teacher.eval()
    m = ConsistencyTraining(teacher, NoiseSchedule(DiffusionConfig()), 0.95, 0.001).eval()
    g = torch.Generator().manual_seed(0)
    z = torch.randn(2, 5, 7, teacher.config.latent_dim, generator=g)
    text = torch.randn(2, 4, teacher.config.text_dim, generator=g)
    t = torch.tensor([999, 259])
    with torch.no_grad():
        ref = teacher(z, t, text)
        for w in (2.0, 7.5):
            out = m.student(z, t, text, guidance=torch.full((2,), w))
            assert torch.allclose(out, ref, atol=1e-5)
    with pytest.raises(ValueError, match="guidance"):
        m.student(z, t, text)
    assert not any(p.requires_grad for p in m.teacher.parameters())
    assert not any(p.requires_grad for p in m.target.parameters())


def test_the_training_state_leaves_out_the_frozen_teacher_and_takes_older_states(tiny_model):
    """The teacher is loaded from its directory at every start, so a training state does not carry
    its weights; a state saved when it did still loads. Moving the module moves the teacher too."""
    from salad.checkpoint import load_state_strict
    from salad.models.io import load_denoiser
    from salad.training.consistency_task import ConsistencyTraining

    teacher, _ = load_denoiser(tiny_model / "denoiser")
    m = ConsistencyTraining(teacher, NoiseSchedule(DiffusionConfig()), 0.95, 0.001)
    state = m.state_dict()
    assert any(k.startswith("student.") for k in state) and not any(k.startswith("teacher.") for k in state)
    assert all(p.data_ptr() != q.data_ptr() for p in m.parameters() for q in teacher.parameters())
    with torch.no_grad():
        for p in m.student.parameters():
            p.add_(1.0)
    old = {**m.state_dict(), **{f"teacher.{k}": v for k, v in teacher.state_dict().items()}}
    fresh = ConsistencyTraining(load_denoiser(tiny_model / "denoiser")[0], NoiseSchedule(DiffusionConfig()), 0.95, 0.001)
    load_state_strict(fresh, old, "an older state")
    for k, v in m.student.state_dict().items():
        assert torch.equal(fresh.student.state_dict()[k], v)
    m.to(torch.float64)
    assert next(m.teacher.parameters()).dtype == torch.float64


def test_distillation_trains_resumes_and_exports_with_its_teacher(tiny_student, tiny_model, tiny_dataset, tmp_path):
    from salad.cli import main
    from salad.models.io import load_denoiser

    student, doc = load_denoiser(tiny_student / "consistency")
    assert student.config.guidance_embedding
    info = doc["meta"]["consistency"]
    _, teacher_doc = load_denoiser(tiny_model / "denoiser")
    assert info["guidance"] == [2.0, 8.0] and info["grid_steps"] == 50
    assert info["teacher"]["sha256"] == teacher_doc["files"]["denoiser"]["sha256"]
    # the guidance embedding left zero is a student that ignores guidance: training moved it
    last = student.guidance_mlp[-1]
    assert last.weight.abs().sum() > 0
    # a resumed run goes on from its state
    run = tmp_path / "run"
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=2)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    consistency_toml(cfg, tiny_dataset, tiny_model, steps=4)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4]
    assert all(np.isfinite(r["loss"]) for r in rows)


def test_the_sampler_timesteps_are_those_of_one_to_four_steps():
    from salad.diffusion.consistency import sampler_timesteps

    s = NoiseSchedule(DiffusionConfig())
    assert sampler_timesteps(s) == [999, 759, 679, 499, 339, 259]
    assert sampler_timesteps(s, 2) == [999, 499]
    with pytest.raises(ValueError, match="descending"):
        s.sampler("dpm", timesteps=[259, 999])
    with pytest.raises(ValueError, match="dpm"):
        s.sampler("ddim", timesteps=[999, 259])


def test_the_trajectory_target_is_the_teachers_own_guided_solve(tiny_model):
    """solve() passes through every sampler timestep, starts from the noise itself, and guides each
    row at its own scale: a row solved in a batch equals it solved alone."""
    from salad.models.io import load_denoiser
    from salad.training.consistency_task import ConsistencyTraining

    teacher, _ = load_denoiser(tiny_model / "denoiser")
    m = ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, "trajectory",
                            teacher_steps=10).eval()
    assert set(m.points) <= set(m.solve_timesteps) and m.solve_timesteps[0] == 999
    g = torch.Generator().manual_seed(0)
    B, D = 3, teacher.config.text_dim
    text = torch.randn(B, 4, D, generator=g)
    batch = {"noise": torch.randn(B, 5, 7, teacher.config.latent_dim, generator=g),
             "guidance": torch.tensor([1.0, 4.0, 9.0]), "frame_mask": None, "auto": torch.zeros(B, dtype=torch.bool),
             "text2": torch.cat((torch.zeros(B, 4, D), text)),
             "text_mask2": torch.cat((torch.zeros(B, 4, dtype=torch.bool), torch.ones(B, 4, dtype=torch.bool))),
             "pooled2": torch.randn(2 * B, D, generator=g)}
    batch["pooled2"][:B] = 0
    states, x0 = m.solve(batch)
    assert states.shape == (len(m.points), *batch["noise"].shape)
    assert torch.equal(states[0], batch["noise"])
    assert not torch.allclose(states[-1], states[0], atol=1e-2)
    # the scale matters, and each row keeps its own
    row = {k: (v[[2, B + 2]] if k.endswith("2") else v[[2]]) if isinstance(v, torch.Tensor) else v
           for k, v in batch.items()}
    _, alone = m.solve(row)
    assert torch.allclose(alone[0], x0[2], atol=1e-4)
    _, other = m.solve(dict(row, guidance=torch.tensor([1.0])))
    assert not torch.allclose(other[0], x0[2], atol=1e-3)


def test_the_distillation_target_guides_as_the_teachers_sampler_does(tiny_model):
    """With cfg_rescale and cfg_cutoff the teacher's guided prediction is sampling's own mix, row by
    row at each row's scale, and the conditional prediction alone below the cutoff."""
    from salad.diffusion.sampling import cfg_combine
    from salad.models.io import load_denoiser
    from salad.training.consistency_task import ConsistencyTraining

    teacher, _ = load_denoiser(tiny_model / "denoiser")
    m = ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, "trajectory",
                            teacher_steps=10, cfg_rescale=0.7, cfg_cutoff=0.3).eval()
    g = torch.Generator().manual_seed(1)
    B, D = 2, teacher.config.text_dim
    text = torch.randn(B, 4, D, generator=g)
    batch = {"guidance": torch.tensor([3.0, 8.0]), "frame_mask": None, "auto": torch.zeros(B, dtype=torch.bool),
             "text2": torch.cat((torch.zeros(B, 4, D), text)),
             "text_mask2": torch.cat((torch.zeros(B, 4, dtype=torch.bool), torch.ones(B, 4, dtype=torch.bool))),
             "pooled2": torch.cat((torch.zeros(B, D), torch.randn(B, D, generator=g)))}
    zt = torch.randn(B, 5, 7, teacher.config.latent_dim, generator=g)
    with torch.no_grad():
        for step in (999, 300, 299, 20):
            t = torch.full((B,), step)
            out = teacher(torch.cat((zt, zt)), torch.cat((t, t)), batch["text2"], batch["text_mask2"], None,
                          pooled_text=batch["pooled2"], auto_length=torch.zeros(2 * B, dtype=torch.bool)).float()
            got = m._guided(zt, t, batch)
            for i, w in enumerate((3.0, 8.0)):
                want = cfg_combine(out[[i, B + i]], w if step >= 300 else 1.0, 0.7)
                torch.testing.assert_close(got[i:i + 1], want, atol=1e-5, rtol=1e-5)
    # below the cutoff the teacher runs the conditional rows alone
    rows = []
    hook = teacher.register_forward_pre_hook(lambda module, args: rows.append(args[0].shape[0]))
    with torch.no_grad():
        for step in (300, 299):
            m._guided(zt, torch.full((B,), step), batch)
    hook.remove()
    assert rows == [2 * B, B]
    plain = ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, "trajectory",
                                teacher_steps=10).eval()
    with torch.no_grad():
        t = torch.full((B,), 999)
        assert not torch.allclose(plain._guided(zt, t, batch), m._guided(zt, t, batch), atol=1e-3)


def test_trajectory_distillation_replays_its_solves_and_resumes(tiny_model, tiny_dataset, tmp_path):
    from salad.cli import main
    from salad.models.io import load_denoiser

    from salad.checkpoint import load_checkpoint

    run, straight = tmp_path / "run", tmp_path / "straight"
    extra = 'target = "trajectory"\nteacher_steps = 6\nreplay = 3\nreplay_buffer = 2'
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=5, extra=extra)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    consistency_toml(cfg, tiny_dataset, tiny_model, steps=8, extra=extra)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(straight)]) == 0
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(1, 9))
    # a solve every third step, the others replay the buffer's; the state saves where the run is in that
    # schedule and what its solves were made from, so the resumed run replays and solves as an unbroken one
    assert [r["solved"] for r in rows] == [1, 0, 0, 1, 0, 0, 1, 0]
    unbroken = [json.loads(line) for line in (straight / "log.jsonl").read_text().splitlines()]
    assert [r["loss"] for r in rows] == [r["loss"] for r in unbroken]
    (_, resumed), (_, whole) = load_checkpoint(run / "state"), load_checkpoint(straight / "state")
    assert resumed["model"].keys() == whole["model"].keys()
    assert all(torch.equal(resumed["model"][k], whole["model"][k]) for k in whole["model"])
    # without a discriminator the batch's latents play no part in a solve, so the state does not carry them
    assert resumed["task"] and not any(k.endswith(".latents") for k in resumed["task"])
    assert all(np.isfinite(r["loss"]) for r in rows)
    student, doc = load_denoiser(run / "model")
    assert doc["meta"]["train_config"]["target"] == "trajectory" and student.guidance_mlp[-1].weight.abs().sum() > 0


def _adversarial_case(tiny_model, lambda_adv: float, seed: int):
    """A trajectory distillation of the tiny teacher with a small discriminator, and three batches of
    latents (3 rows of 5 frames): the student's estimates (requiring grad), their target, the real side."""
    from salad.models.discriminator import DiscriminatorConfig, PromptDiscriminator
    from salad.models.io import load_denoiser
    from salad.training.consistency_task import ConsistencyTraining

    teacher, _ = load_denoiser(tiny_model / "denoiser")
    c = teacher.config
    torch.manual_seed(0)
    disc = PromptDiscriminator(c.parts * c.latent_dim, c.text_dim, DiscriminatorConfig(width=8, levels=1))
    m = ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, "trajectory",
                            teacher_steps=6, discriminator=disc, lambda_adv=lambda_adv)
    g = torch.Generator().manual_seed(seed)
    pred, target, real = (torch.randn(3, 5, c.parts, c.latent_dim, generator=g) for _ in range(3))
    return m, teacher, pred.requires_grad_(True), target, real


def test_the_adversarial_term_is_held_at_its_share_of_the_students_gradient(tiny_model):
    """The student's adversarial gradient on its clean estimates is lambda_adv times the consistency
    loss's, whatever the discriminator's scale; the discriminator's own loss reaches only it."""
    from salad.training.consistency_task import ConsistencyTraining

    m, teacher, pred, target, real = _adversarial_case(tiny_model, 0.25, seed=0)
    disc, c = m.disc, teacher.config
    cond = {"frame_mask": torch.arange(5)[None] < torch.tensor([[5], [3], [4]]), "pooled": torch.randn(3, c.text_dim)}
    for scale in (1.0, 30.0):
        with torch.no_grad():
            disc.san.weight.mul_(scale)
        loss = m._huber(pred, target, cond["frame_mask"])
        total, logs = m._with_adversarial(loss, pred, real, cond, {})
        g_rec, = torch.autograd.grad(loss, pred, retain_graph=True)
        g_all, = torch.autograd.grad(total, pred, retain_graph=True)
        assert float((g_all - g_rec).norm() / g_rec.norm()) == pytest.approx(0.25, rel=1e-3)
        assert {"g_adv", "adv_weight", "d_gap", "d_real", "d_fake"} <= set(logs)
        # the discriminator learns from its loss: its parameters get gradient, the teacher's none
        grads = torch.autograd.grad(total, list(disc.parameters()))
        assert all(float(x.abs().sum()) > 0 for x in grads)
    assert ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001,
                               discriminator=disc, lambda_adv=0.0).disc is None
    with pytest.raises(ValueError, match="lambda_adv"):
        ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, lambda_adv=0.5)


def test_the_discriminator_can_judge_chosen_rows_alone(tiny_model):
    """With adversarial_rows (the rows in focus), the other rows get no adversarial gradient and their real side does not
    reach the discriminator; the judged rows' share is lambda_adv of their own consistency gradient."""
    m, teacher, pred, target, real = _adversarial_case(tiny_model, 0.5, seed=1)
    c = teacher.config
    g = torch.Generator().manual_seed(2)
    rows = torch.tensor([True, False, True])
    cond = {"frame_mask": None, "pooled": torch.randn(3, c.text_dim, generator=g), "adversarial_rows": rows}
    loss = m._huber(pred, target, None)
    total, logs = m._with_adversarial(loss, pred, real, cond, {})
    g_rec, = torch.autograd.grad(loss, pred, retain_graph=True)
    g_all, = torch.autograd.grad(total, pred, retain_graph=True)
    extra = g_all - g_rec
    assert float(extra[1].abs().max()) == 0.0 and float(extra[rows].abs().max()) > 0
    assert float(extra.norm() / g_rec[rows].norm()) == pytest.approx(0.5, rel=1e-3)
    assert logs["judged_rows"] == pytest.approx(2 / 3)
    other = real.clone()
    other[1] += 5.0
    again, _ = m._with_adversarial(m._huber(pred, target, None), pred, other, cond, {})
    torch.testing.assert_close(again, total)
    cond["adversarial_rows"] = torch.zeros(3, dtype=torch.bool)
    none, logs = m._with_adversarial(loss, pred, real, cond, {})
    assert none is loss and logs["judged_rows"] == 0.0


def test_distillation_can_judge_the_rare_actions_alone(tiny_model, tiny_dataset, tmp_path, capsys):
    """focus_max_clips marks the rows of content classes with at most that many training clips,
    replayed solves keep their marks, and a count that splits no class is refused."""
    from salad.cli import main
    from salad.config import load_toml
    from salad.training.configs import ConsistencyTrainConfig
    from salad.training.consistency_task import ConsistencyTask

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)          # 2 kicks, 6 walks in train
    extra = ('target = "trajectory"\nteacher_steps = 6\nreplay = 2\nlambda_adv = 0.5\nfocus_max_clips = {}\n'
             '[discriminator]\nwidth = 8\nlevels = 1\nblocks_per_level = 1')
    cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=4, extra=extra.format(2))
    task = ConsistencyTask(load_toml(ConsistencyTrainConfig, cfg), show_progress=False)
    kicks = np.array([caps == ["a person kicks"] for caps in task.data.captions])
    rng = np.random.default_rng(0)
    first = task.batch(rng)                                        # a fresh solve: stored with its marks
    task.model(first)
    assert torch.equal(task.model._solves[-1]["adversarial_rows"], first["adversarial_rows"])
    for _ in range(6):
        b = task.batch(rng)
        if "rows" in b:
            assert b["adversarial_rows"].tolist() == kicks[b["rows"].numpy()].tolist()
    run = tmp_path / "run"
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    logs = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert all(0.0 <= r["judged_rows"] <= 1.0 for r in logs)
    for clips, words in ((1, "every content class out of focus"), (6, "no content class out of focus")):
        cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=1, extra=extra.format(clips))
        assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / f"r{clips}")]) == 2
        assert f"focus_max_clips = {clips} leaves {words}" in capsys.readouterr().err
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=1, extra=extra.format(2))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "unlabelled")]) == 2
    assert "focus picks actions by their content class, and this data has no content labels" in capsys.readouterr().err


def test_distillation_can_judge_named_actions_alone(tiny_model, tiny_dataset, tmp_path, capsys):
    """focus_classes marks the rows of the named content classes, whatever their counts; a class the
    data lacks is refused with the ones it has, and so is naming classes beside focus_max_clips."""
    from salad.cli import main
    from salad.config import load_toml
    from salad.training.configs import ConsistencyTrainConfig
    from salad.training.consistency_task import ConsistencyTask

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)          # 2 kicks, 6 walks in train
    extra = ('target = "trajectory"\nteacher_steps = 6\nreplay = 2\nlambda_adv = 0.5\nfocus_classes = {}\n'
             '[discriminator]\nwidth = 8\nlevels = 1\nblocks_per_level = 1')
    for classes in (["walk"], ["kick"]):
        cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=2, extra=extra.format(json.dumps(classes)))
        task = ConsistencyTask(load_toml(ConsistencyTrainConfig, cfg), show_progress=False)
        kicks = np.array([caps == ["a person kicks"] for caps in task.data.captions])
        b = task.batch(np.random.default_rng(0))
        want = kicks[b["rows"].numpy()]
        assert b["adversarial_rows"].tolist() == (want if classes == ["kick"] else ~want).tolist()
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run")]) == 0
    cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=1, extra=extra.format('["kick", "slash"]'))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r1")]) == 2
    assert "focus_classes names ['slash'], which no training motion has; the content classes are kick, walk" \
        in capsys.readouterr().err
    cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=1,
                           extra=extra.format('["kick"]').replace("lambda_adv", "focus_max_clips = 2\nlambda_adv"))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r2")]) == 2
    assert "focus_classes must be empty when focus_max_clips picks the actions" in capsys.readouterr().err


def test_judged_actions_can_take_rows_of_every_solved_batch(tiny_model, tiny_dataset, tmp_path, capsys):
    """focus_rows puts that many of the judged actions' motions first in every batch the teacher
    solves, and the replays train on those solves, so every step judges them whatever the draw; it
    needs judged actions and a batch to fit in."""
    from salad.cli import main
    from salad.config import load_toml
    from salad.training.configs import ConsistencyTrainConfig
    from salad.training.consistency_task import ConsistencyTask

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)          # 2 kicks, 6 walks in train
    extra = ('target = "trajectory"\nteacher_steps = 6\nreplay = 2\nlambda_adv = 0.5\n{}focus_rows = {}\n'
             '[discriminator]\nwidth = 8\nlevels = 1\nblocks_per_level = 1')
    judged = 'focus_classes = ["kick"]\n'
    cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=4, extra=extra.format(judged, 2))
    task = ConsistencyTask(load_toml(ConsistencyTrainConfig, cfg), show_progress=False)
    kicks = np.array([caps == ["a person kicks"] for caps in task.data.captions])
    rng, fresh = np.random.default_rng(0), 0
    for _ in range(8):
        b = task.batch(rng)
        if "rows" in b:                                            # a solved batch, not a replay of one
            fresh += 1
            assert kicks[b["rows"][:2].numpy()].all() and b["adversarial_rows"][:2].all()
            assert b["adversarial_rows"].tolist() == kicks[b["rows"].numpy()].tolist()
    assert fresh == 4
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run")]) == 0
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert len(rows) == 4 and all(r["judged_rows"] >= 0.5 for r in rows), "2 rows of 4 at every step"
    for text, words in ((extra.format(judged, 5), "focus_rows must be in 0..optim.batch_size (4), got 5"),
                        (extra.format("", 1), "focus_rows must be 0 unless focus_classes or")):
        cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=1, extra=text)
        assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "bad")]) == 2
        assert words in capsys.readouterr().err


def test_named_actions_can_take_rows_of_every_solved_batch_with_no_discriminator(tiny_model, tiny_dataset, tmp_path,
                                                                               capsys):
    """With lambda_adv = 0, focus_rows still puts the named actions' motions first in every solved
    batch (more of their solves for the consistency loss), and nothing is judged."""
    from salad.cli import main
    from salad.config import load_toml
    from salad.training.configs import ConsistencyTrainConfig
    from salad.training.consistency_task import ConsistencyTask

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)          # 2 kicks, 6 walks in train
    extra = 'target = "trajectory"\nteacher_steps = 6\nreplay = 2\nfocus_classes = ["kick"]\nfocus_rows = 3\n'
    cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=4, extra=extra)
    task = ConsistencyTask(load_toml(ConsistencyTrainConfig, cfg), show_progress=False)
    assert task.model.disc is None
    kicks = np.array([caps == ["a person kicks"] for caps in task.data.captions])
    rng, fresh = np.random.default_rng(0), 0
    for _ in range(8):
        b = task.batch(rng)
        if "rows" in b:
            fresh += 1
            assert kicks[b["rows"][:3].numpy()].all() and "adversarial_rows" not in b
    assert fresh == 4
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run")]) == 0
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert len(rows) == 4 and all("judged_rows" not in r for r in rows)

    # the settings were called adversarial_* before: a config with the old names is told the new ones, and a
    # run whose state stored them resumes
    old = {"focus_classes": "adversarial_classes", "focus_rows": "adversarial_rows",
           "focus_max_clips": "adversarial_max_clips"}
    stale = tmp_path / "old.toml"
    stale.write_text(cfg.read_text().replace("focus_classes", "adversarial_classes").replace("focus_rows",
                                                                                            "adversarial_rows"))
    assert main(["train", "consistency", "--config", str(stale), "--out-dir", str(tmp_path / "stale")]) == 2
    assert ("renamed key(s): adversarial_classes is now focus_classes; adversarial_rows is now focus_rows"
            in capsys.readouterr().err)
    state = tmp_path / "run" / "state" / "config.json"
    doc = json.loads(state.read_text())
    doc["config"] = {old.get(k, k): v for k, v in doc["config"].items()}
    assert "adversarial_rows" in doc["config"]
    state.write_text(json.dumps(doc))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run"),
                 "--max-steps", "6"]) == 0
    assert "resumed" in capsys.readouterr().err
    assert len((tmp_path / "run" / "log.jsonl").read_text().splitlines()) == 6


def test_distillation_can_cross_captions_and_reads_them_with_the_text_encoder(tiny_model, tiny_dataset, tmp_path,
                                                                            capsys):
    """caption_crossover gives rows wordings no clip has, crossed from two rows' captions, each with the
    text encoder's own features of it (the teacher solves them like any other), and trains on them;
    with the lcd target, whose rows are the captures themselves, it is refused."""
    from salad.cli import main
    from salad.config import load_toml
    from salad.training.configs import ConsistencyTrainConfig
    from salad.training.consistency_task import ConsistencyTask

    extra = 'target = "{}"\nteacher_steps = 6\nreplay = 1\ncaption_crossover = 1.0\n'
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=2, extra=extra.format("trajectory"))
    task = ConsistencyTask(load_toml(ConsistencyTrainConfig, cfg), show_progress=False)
    known = {c for cs in task.data.captions for c in cs}
    rng, new = np.random.default_rng(0), 0
    for _ in range(6):
        b = task.batch(rng)
        new += sum(c not in known for c in b["captions"])
        f = task.data.text_encoder.encode(b["captions"])
        n = f.tokens.shape[1]
        assert torch.equal(b["text_mask"][:, :n], f.mask) and not b["text_mask"][:, n:].any()
        assert torch.allclose(b["text"][:, :n], f.tokens, atol=0.02 * float(f.tokens.abs().max()))
        assert torch.allclose(b["pooled"], f.pooled, atol=1e-5)
    assert new >= 6, "crossed wordings in the batches"
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run")]) == 0
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=1, extra=extra.format("lcd"))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "bad")]) == 2
    assert 'caption_crossover must be 0 with target = "lcd"' in capsys.readouterr().err


def test_the_teachers_stochastic_samples_can_be_the_discriminators_real_side(tiny_model):
    """adversarial_real = "teacher": the real side of a solved batch is the teacher sampled as the
    studio samples it (SDE-DPM-Solver++, guided at the row's scale, rescaled and cut off alike), from
    fresh noise, not the batch's captures nor the deterministic solve."""
    from salad.diffusion.sampling import fresh_noise, sample
    from salad.models.discriminator import DiscriminatorConfig, PromptDiscriminator
    from salad.models.io import load_denoiser
    from salad.training.consistency_task import ConsistencyTraining

    teacher, _ = load_denoiser(tiny_model / "denoiser")
    c = teacher.config
    disc = PromptDiscriminator(c.parts * c.latent_dim, c.text_dim, DiscriminatorConfig(width=8, levels=1))
    m = ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, "trajectory",
                            teacher_steps=8, cfg_rescale=0.7, cfg_cutoff=0.3, discriminator=disc, lambda_adv=0.3,
                            adversarial_real="teacher").eval()
    g = torch.Generator().manual_seed(2)
    D = c.text_dim
    text = torch.randn(1, 4, D, generator=g)
    batch = {"noise": torch.randn(1, 5, c.parts, c.latent_dim, generator=g),
             "latents": torch.randn(1, 5, c.parts, c.latent_dim, generator=g),
             "guidance": torch.tensor([4.0]), "frame_mask": None, "auto": torch.zeros(1, dtype=torch.bool),
             "text2": torch.cat((torch.zeros(1, 4, D), text)),
             "text_mask2": torch.cat((torch.zeros(1, 4, dtype=torch.bool), torch.ones(1, 4, dtype=torch.bool))),
             "pooled2": torch.cat((torch.zeros(1, D), torch.randn(1, D, generator=g)))}

    def model(x2, t2):
        return teacher(x2, t2, batch["text2"], batch["text_mask2"], None, pooled_text=batch["pooled2"],
                       auto_length=torch.zeros(2, dtype=torch.bool))

    studio = torch.Generator().manual_seed(5)
    want = sample(model, fresh_noise(batch["noise"], studio), m.schedule, "dpm-sde", 8, cfg_scale=4.0,
                  cfg_rescale=0.7, cfg_cutoff=0.3, generator=studio)
    batch["sde_seed"] = torch.tensor(5)
    real = m._real_for(batch)
    torch.testing.assert_close(real, want, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(m._real_for(batch), real)                  # the batch's seed decides
    _, solved = m.solve(batch)
    assert not torch.allclose(real, solved, atol=1e-2) and not torch.allclose(real, batch["latents"], atol=1e-2)
    batch["sde_seed"] = torch.tensor(6)
    assert not torch.allclose(m._real_for(batch), real, atol=1e-2)       # fresh noise for each solve
    with pytest.raises(ValueError, match="trajectory"):
        ConsistencyTraining(teacher.eval(), NoiseSchedule(DiffusionConfig()), 0.95, 0.001, "lcd",
                            discriminator=disc, lambda_adv=0.3, adversarial_real="teacher")


@pytest.mark.parametrize("space, real, target", [("latents", "data", "trajectory"), ("motion", "teacher", "trajectory"),
                                                 ("motion", "data", "lcd")])
def test_adversarial_distillation_trains_and_resumes(tiny_model, tiny_dataset, tmp_path, space, real, target):
    from salad.checkpoint import load_checkpoint
    from salad.cli import main

    run = tmp_path / "run"
    extra = (f'target = "{target}"\nteacher_steps = 6\nreplay = 2\nlambda_adv = 0.5\nadversarial_space = "{space}"\n'
             f'adversarial_real = "{real}"\n'
             '[discriminator]\nwidth = 8\nlevels = 1\nblocks_per_level = 1')
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=3, extra=extra)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    _, parts = load_checkpoint(run / "state")
    assert not any(k.startswith(("teacher.", "decoder.")) for k in parts["model"])
    first = {k: v.clone() for k, v in parts["model"].items() if k.startswith("disc.")}
    assert first and any(k.startswith("disc.text.") for k in first)
    # the discriminator reads 263-d decoded frames or the latents, plus the prompt's 32 channels
    from salad.models.io import load_denoiser
    c = load_denoiser(tiny_model / "denoiser")[0].config
    width = parts["model"]["disc.san.features.0.weight"].shape[1] - 32
    assert width == (263 if space == "motion" else c.parts * c.latent_dim)
    consistency_toml(cfg, tiny_dataset, tiny_model, steps=5, extra=extra)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5]
    assert all(np.isfinite(r["g_adv"]) and r["adv_weight"] > 0 and np.isfinite(r["d_gap"]) for r in rows)
    _, parts = load_checkpoint(run / "state")
    assert any(not torch.equal(parts["model"][k], v) for k, v in first.items())
    # the export is the student alone: it loads as any student does
    from salad.models.io import load_consistency_student
    student, _, _ = load_consistency_student(run / "model")
    assert not any(k.startswith("disc") for k in student.state_dict())


def test_distillation_exports_the_checkpoint_its_validation_judges_best(tiny_model, tiny_dataset, tmp_path, capsys):
    """select_from judges every checkpoint from that step on by the fidelity checks of the actions in focus,
    on motions from their training captions, logs each judgement, and model/ holds the best-judged one
    (the first of equals); it is refused without actions to judge, or past the run's last step."""
    from salad.checkpoint import read_checkpoint_config
    from salad.cli import main

    from salad.data.captions import caption_line

    root = labelled_copy(tiny_dataset, tmp_path, kicks=2)
    second = root / "texts" / f"{(root / 'train.txt').read_text().split()[1]}.txt"
    second.write_text(second.read_text() + caption_line("a person kicks high") + "\n")    # two kick captions
    cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=6,
                           extra='focus_classes = ["kick"]\nselect_from = 4\nselect_captions = 1')
    run = tmp_path / "run"
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    judged = [json.loads(line) for line in (run / "val.jsonl").read_text().splitlines()]
    assert [r["step"] for r in judged] == [4, 6]                       # checkpoints every 2 steps, from step 4
    assert all(set(r["classes"]) == {"kick"} and r["passed"] in (0, 1) for r in judged)
    # what each judgement cost (a tiny model's may round to 0.0 s)
    assert all(r["motions"] == 8 and isinstance(r["seconds"], float) and r["seconds"] >= 0 for r in judged)
    assert all(r["score"] == pytest.approx(r["passed"] + 0.49 * r["margin"], abs=1e-3) for r in judged)
    best = max(judged, key=lambda r: r["score"])
    meta = read_checkpoint_config(run / "model", "denoiser")["meta"]
    assert meta["step"] == best["step"] and meta["val"]["score"] == best["score"]
    assert set(meta["val"]["classes"]["kick"]["checks"]) == {"duration_s", "leg_lift_m", "jerk_mps3"}
    assert meta["val"]["classes"]["kick"]["motions"] == 8                # one of the two captions x 8 seeds
    assert main(["generate", "a person kicks", "--model", str(_with_student(tiny_model, run, tmp_path)),
                 "--sampler", "consistency", "-o", str(tmp_path / "k.npy")]) == 0
    # judging draws none of the run's random numbers: the same run unjudged trains step for step alike
    plain = consistency_toml(tmp_path / "p.toml", root, tiny_model, steps=6, extra='focus_classes = ["kick"]')
    assert main(["train", "consistency", "--config", str(plain), "--out-dir", str(tmp_path / "plain")]) == 0
    losses = [[json.loads(line)["loss"] for line in (r / "log.jsonl").read_text().splitlines()]
              for r in (run, tmp_path / "plain")]
    assert len(losses[0]) == 6 and losses[0] == losses[1]
    for extra, message in (("select_from = 2", "select_from must be 0 unless focus_classes or focus_max_clips"),
                           ('focus_classes = ["kick"]\nselect_from = 8', "select_from must be in 0..optim.max_steps (6)")):
        cfg = consistency_toml(tmp_path / "c.toml", root, tiny_model, steps=6, extra=extra)
        assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r")]) == 2
        assert message in capsys.readouterr().err


def _with_student(model, run, where):
    """A copy of the model directory with the run's exported student as its consistency/."""
    out = where / "with-student"
    shutil.copytree(model, out)
    shutil.copytree(run / "model", out / "consistency")
    return out


def test_distillation_config_errors_are_clear(tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    for extra, message in (('target = "progressive"', "target must be one of lcd, trajectory"),
                           ("replay = 0", "replay must be >= 1"),
                           ("cfg_cutoff = 1.0", "cfg_cutoff must be in [0, 1)"),
                           ("lambda_adv = -0.1", "lambda_adv must be >= 0"),
                           ('adversarial_space = "pixels"', "adversarial_space must be latents or motion"),
                           ('adversarial_real = "teacher"', 'adversarial_real must be "data" with target = "lcd"'),
                           ('adversarial_real = "studio"', "adversarial_real must be one of data, teacher"),
                           ("focus_max_clips = -1", "focus_max_clips must be >= 0"),
                           ("select_captions = 0", "select_captions must be >= 1")):
        cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=1, extra=extra)
        assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r")]) == 2
        assert message in capsys.readouterr().err


def test_distillation_refuses_a_student_as_teacher_and_a_teacher_flag_elsewhere(tiny_student, tiny_dataset,
                                                                                  tmp_path, capsys):
    from salad.cli import main

    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "vae").symlink_to((tiny_student / "vae").resolve())
    (fake / "denoiser").symlink_to((tiny_student / "consistency").resolve())
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, fake, steps=1)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r")]) == 2
    assert "distilled student already" in capsys.readouterr().err
    assert main(["train", "denoiser", "--config", str(cfg), "--teacher", str(fake)]) == 2
    assert "--teacher applies to consistency" in capsys.readouterr().err


# ---------------------------------------------------------------- pipeline

@pytest.fixture(scope="module")
def student_pipe(tiny_student):
    """The tiny student's pipeline, without the planted-feet refinement: its line search through the tiny
    VAE would magnify the last digits in which the fused and the watched attention paths differ."""
    from salad.pipeline import load_pipeline

    pipe = load_pipeline(tiny_student, bf16=False)
    pipe.set_foot_refine(0)
    return pipe


def test_pipeline_without_a_student_says_how_to_get_one(pipe):
    with pytest.raises(ValueError, match="salad train consistency"):
        pipe.generate("a person walks forward", seconds=2, sampler="consistency")


@pytest.mark.parametrize("steps", [1, 4])
def test_consistency_generate_runs_the_student_with_attention(student_pipe, steps):
    calls = []
    m = student_pipe.generate("a person walks forward", seconds=2, seed=3, sampler="consistency", steps=steps,
                              return_attention=True, progress=lambda i, n: calls.append(i))
    assert m.joints.shape[0] == 40 and np.isfinite(m.joints).all()
    assert calls == list(range(1, steps + 1))
    assert m.attention.steps == steps and np.isfinite(m.attention.data).all()
    assert m.attention.words == ["a", "person", "walks", "forward"]
    again = student_pipe.generate("a person walks forward", seconds=2, seed=3, sampler="consistency", steps=steps)
    assert np.allclose(again.joints, m.joints, atol=1e-5)


def test_consistency_default_steps_and_bounds(student_pipe):
    assert student_pipe.check_sampling(None, 5.0, "consistency")[0] == 4
    assert student_pipe.check_sampling(None, 5.0, "ddim")[0] == 50
    with pytest.raises(ValueError, match="1..50"):
        student_pipe.generate("a person walks forward", seconds=2, sampler="consistency", steps=51)
    with pytest.raises(ValueError, match="distilled for cfg 2..8"):
        student_pipe.generate("a person walks forward", seconds=2, sampler="consistency", cfg=12.0)


@pytest.mark.parametrize("mode,kw", [("swap", dict(target_prompt="a person walks backward")),
                                     ("refine", dict(target_prompt="a person walks forward slowly")),
                                     ("reweight", dict(reweight={"forward": 2.0})),
                                     ("mirror", dict(mirror="all"))])
def test_consistency_edits_run_all_four_modes(student_pipe, mode, kw):
    res = student_pipe.edit("a person walks forward", mode=mode, seconds=2, seed=1, sampler="consistency", **kw)
    assert res.source.joints.shape == res.edited.joints.shape
    assert res.params["sampler"] == "consistency" and res.params["steps"] == 4
    assert res.source.attention is not None and res.edited.attention is not None


def test_consistency_edit_keeps_the_source_of_a_plain_generate(student_pipe):
    """The source branch of an edit is the motion generate gives for the same seed."""
    res = student_pipe.edit("a person walks forward", target_prompt="a person walks backward",
                            mode="swap", seconds=2, seed=5, sampler="consistency")
    alone = student_pipe.generate("a person walks forward", seconds=2, seed=5, sampler="consistency")
    assert np.allclose(res.source.joints, alone.joints, atol=1e-4)


def test_a_teacher_checkpoint_is_not_taken_for_a_student(tiny_student, tmp_path):
    from salad.checkpoint import CheckpointError
    from salad.pipeline import load_pipeline

    model = tmp_path / "m"
    model.mkdir()
    for part in ("vae", "denoiser"):
        (model / part).symlink_to((tiny_student / part).resolve())
    (model / "consistency").symlink_to((tiny_student / "denoiser").resolve())
    with pytest.raises(CheckpointError, match="not a consistency-distilled student"):
        load_pipeline(model)


def test_the_student_is_preferred_only_where_its_checkpoint_says_so(tiny_student, student_pipe, tmp_path):
    from salad.checkpoint import CheckpointError
    from salad.pipeline import load_pipeline

    # a fresh distillation records no measurement, so it is preferred nowhere
    assert not student_pipe.student_preferred("text") and not student_pipe.student_preferred("control")
    with pytest.raises(ValueError, match="use must be one of text, edit, control"):
        student_pipe.student_preferred("generate")

    def with_uses(uses):
        model = tmp_path / f"m{len(list(tmp_path.iterdir()))}"
        model.mkdir()
        for part in ("vae", "denoiser"):
            (model / part).symlink_to((tiny_student / part).resolve())
        shutil.copytree(tiny_student / "consistency", model / "consistency")
        doc = json.loads((model / "consistency" / "config.json").read_text())
        doc["meta"]["consistency"]["default_for"] = uses
        (model / "consistency" / "config.json").write_text(json.dumps(doc))
        return model

    measured = load_pipeline(with_uses(["control"]), bf16=False)
    assert measured.student_preferred("control") and not measured.student_preferred("text")
    assert not measured.student_preferred("edit")
    edits = load_pipeline(with_uses(["edit"]), bf16=False)
    assert edits.student_preferred("edit") and not edits.student_preferred("text")
    for bad in (["generate"], "control"):
        with pytest.raises(CheckpointError, match="default_for must be a list drawn from text, edit, control"):
            load_pipeline(with_uses(bad))


def test_consistency_control_follows_targets_and_composes_with_an_edit(student_pipe):
    from salad.motion.control import control_errors, make_signal

    kept = student_pipe.projections
    student_pipe.set_projections(0)      # control decodes without projection: the same motion unguided
    try:
        free = student_pipe.generate("a person walks forward", seconds=1.6, seed=5, sampler="consistency")
    finally:
        student_pipe.set_projections(kept)
    targets = free.joints.copy()
    targets[:, 0, 0] += 0.5                       # the pelvis half a metre to the left
    mask = np.zeros((32, 22), dtype=bool)
    mask[:, 0] = True
    sig = make_signal(targets, mask)
    steps = []
    guided = student_pipe.control("a person walks forward", signal=sig, seed=5, sampler="consistency",
                                  progress=lambda i, n: steps.append(n))
    assert steps == [4] * 4
    from salad.diffusion.guidance import STUDENT_REFINE_STEPS
    assert guided.info["control_refine_steps"] == STUDENT_REFINE_STEPS < 50
    before = np.abs(free.joints[:, 0, 0] - targets[:, 0, 0]).mean()
    assert control_errors(guided.joints, sig).mean() < 0.5 * before
    off = student_pipe.control("a person walks forward", signal=sig, seed=5, sampler="consistency", strength=0.0)
    np.testing.assert_allclose(off.joints, free.joints, atol=5e-3)
    res = student_pipe.control("a person walks forward", signal=sig, seed=5, sampler="consistency",
                               edit={"mirror": "all"})
    assert res.params["sampler"] == "consistency" and res.params["steps"] == 4
    assert control_errors(res.edited.joints, sig).mean() < 0.5 * before
    with pytest.raises(ValueError, match="time-travel"):
        student_pipe.control("a person walks forward", signal=sig, sampler="consistency", repeats=2)
    with pytest.raises(ValueError, match="ddim or consistency"):
        student_pipe.control("a person walks forward", signal=sig, sampler="dpm")


def test_consistency_real_edit_keeps_the_reconstruction_exactly(student_pipe, tiny_dataset):
    from salad.editing.real import decode, encode, read_real

    name = (tiny_dataset / "test.txt").read_text().split()[0]
    feats = np.load(tiny_dataset / "new_joint_vecs" / f"{name}.npy")
    real = read_real(student_pipe, feats, trim=True)
    vae = decode(student_pipe, encode(student_pipe, real), ["a person walks forward"])[0]
    res = student_pipe.edit_real(feats, "a person walks forward", "a person walks backward", mode="swap",
                                 sampler="consistency", trim=True)
    np.testing.assert_allclose(res.source.joints, vae.joints, atol=1e-3)
    assert np.abs(res.edited.joints - res.source.joints).max() > 1e-3
    assert res.params["sampler"] == "consistency" and res.params["steps"] == 4
    assert res.source.info["mpjpe_m"] >= 0 and res.edited.attention.words[2] == "walks"
    with pytest.raises(ValueError, match="ddim .*or consistency"):
        student_pipe.edit_real(feats, "a person walks forward", mode="mirror", sampler="dpm", trim=True)


def test_cli_samples_with_the_student(tiny_student, tiny_dataset, tmp_path, capsys):
    from salad.cli import main
    from salad.cli.common import SAMPLER_CHOICES
    from salad.diffusion.schedule import SAMPLERS

    assert SAMPLER_CHOICES == SAMPLERS
    out = tmp_path / "walk.npy"
    assert main(["generate", "a person walks forward", "--seconds", "2", "--sampler", "consistency", "--cfg", "5",
                 "--model", str(tiny_student), "-o", str(out)]) == 0
    assert np.load(out).shape[0] == 40
    name = (tiny_dataset / "test.txt").read_text().split()[0]
    edited = tmp_path / "edited.npy"
    assert main(["edit-real", str(tiny_dataset / "new_joint_vecs" / f"{name}.npy"), "--source",
                 "a person walks forward", "--mode", "mirror", "--mirror", "all", "--sampler", "consistency",
                 "--trim", "--model", str(tiny_student), "-o", str(edited)]) == 0
    assert "student edit" in capsys.readouterr().out and edited.exists()
    assert main(["generate", "a person walks forward", "--sampler", "consistency", "--cfg", "20",
                 "--model", str(tiny_student), "-o", str(out)]) == 2
    assert "distilled for cfg" in capsys.readouterr().err


def _model_dir_and_another_denoiser(tiny_model, tiny_dataset, tmp_path):
    """A model directory with the tiny model's VAE and no denoiser yet, and a second denoiser on that
    VAE (trained for one step), for tests that swap a teacher."""
    from salad.cli import main

    other = tmp_path / "other"
    other.mkdir()
    (other / "vae").symlink_to((tiny_model / "vae").resolve())
    cfg = denoiser_toml(tmp_path / "d.toml", tiny_dataset, steps=1)
    assert main(["train", "denoiser", "--config", str(cfg), "--out-dir", str(tmp_path / "den"),
                 "--vae", str(tiny_model / "vae")]) == 0
    return other, tmp_path / "den" / "model"


def test_distillation_continues_an_exported_student_of_the_same_teacher(tiny_student, tiny_model, tiny_dataset,
                                                                          tmp_path, capsys):
    from salad.cli import main
    from salad.models.io import load_denoiser

    student, before = load_denoiser(tiny_student / "consistency")
    start = before["meta"]["step"]
    run = tmp_path / "more"
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, tiny_model, steps=start)
    # zero more steps to take is a clear error, not a silent no-op
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run),
                 "--continue-from", str(tiny_student / "consistency")]) == 2
    assert "--max-steps above" in capsys.readouterr().err
    # a long re-warm-up keeps these two steps' updates tiny, so the export must still be the student
    consistency_toml(cfg, tiny_dataset, tiny_model, steps=start + 2)
    cfg.write_text(cfg.read_text().replace("warmup_steps = 1\n", "warmup_steps = 10000\n"))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run),
                 "--continue-from", str(tiny_student / "consistency")]) == 0
    after, doc = load_denoiser(run / "model")
    assert doc["meta"]["step"] == start + 2
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [start + 1, start + 2]
    # it went on from the student, not from the teacher (whose copy starts with the guidance embedding at zero)
    old, new = student.guidance_mlp[-1].weight, after.guidance_mlp[-1].weight
    assert old.abs().sum() > 0 and torch.allclose(new, old, atol=1e-4)
    for (name, a), b in zip(student.state_dict().items(), after.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-4), name
    # a student of another teacher is refused
    other, newer = _model_dir_and_another_denoiser(tiny_model, tiny_dataset, tmp_path)
    (other / "denoiser").symlink_to(newer)
    capsys.readouterr()
    consistency_toml(cfg, tiny_dataset, other, steps=start + 2)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r2"),
                 "--continue-from", str(tiny_student / "consistency")]) == 2
    assert "distilled from another teacher" in capsys.readouterr().err
    # ...but it may start a new run for it (a fine-tuned teacher's student starts from the old student)
    cfg.write_text(cfg.read_text().replace("warmup_steps = 1\n", "warmup_steps = 10000\n"))
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "r3"),
                 "--init-from", str(tiny_student / "consistency")]) == 0
    fresh, doc = load_denoiser(tmp_path / "r3" / "model")
    rows = [json.loads(line) for line in (tmp_path / "r3" / "log.jsonl").read_text().splitlines()]
    assert rows[0]["step"] == 1 and doc["meta"]["step"] == start + 2       # all of max_steps, from step 0
    assert doc["meta"]["consistency"]["teacher"]["sha256"] != before["meta"]["consistency"]["teacher"]["sha256"]
    assert torch.allclose(fresh.guidance_mlp[-1].weight, old, atol=1e-4)


def test_a_run_does_not_resume_onto_another_teacher(tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    other, newer = _model_dir_and_another_denoiser(tiny_model, tiny_dataset, tmp_path)
    # the teacher directory keeps its path while its denoiser is replaced by a newer one
    (other / "denoiser").symlink_to((tiny_model / "denoiser").resolve())
    run = tmp_path / "run"
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, other, steps=2)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 0
    (other / "denoiser").unlink()
    (other / "denoiser").symlink_to(newer)
    consistency_toml(cfg, tiny_dataset, other, steps=3)
    capsys.readouterr()
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(run)]) == 2
    assert "differs in ['teacher_sha256']" in capsys.readouterr().err


def test_a_narrow_student_learns_from_a_widened_teacher(tiny_student, tiny_model, tiny_dataset, tmp_path, capsys):
    from salad.cli import main
    from salad.config import from_dict
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.io import load_denoiser, save_denoiser
    from salad.models.widen import widen
    from salad.pipeline import load_pipeline

    narrow, doc = load_denoiser(tiny_model / "denoiser")
    c = doc["config"]
    wide = tmp_path / "wide"
    wide.mkdir()
    (wide / "vae").symlink_to((tiny_model / "vae").resolve())
    save_denoiser(wide / "denoiser", widen(narrow), from_dict(DiffusionConfig, c["diffusion"]), c["text_encoder"],
                  c["canvas_frames"], c["vae_checksum"], meta=doc["meta"])
    cfg = consistency_toml(tmp_path / "c.toml", tiny_dataset, wide, steps=2,
                           extra=f'student = "{tiny_student / "consistency"}"')
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run")]) == 0
    student, sdoc = load_denoiser(tmp_path / "run" / "model")
    _, wdoc = load_denoiser(wide / "denoiser")
    assert student.config.dim == narrow.config.dim and student.config.guidance_embedding
    assert sdoc["meta"]["consistency"]["teacher"]["sha256"] == wdoc["files"]["denoiser"]["sha256"]
    start, _ = load_denoiser(tiny_student / "consistency")
    assert not torch.allclose(student.output[-1].weight, start.output[-1].weight)     # it trained from there
    # the pair loads and samples: the wide teacher for DDIM, the narrow student for the consistency sampler
    (wide / "consistency").symlink_to(tmp_path / "run" / "model")
    pipe = load_pipeline(wide)
    assert pipe.denoiser.config.dim == 2 * pipe.student.config.dim
    for sampler, steps in (("ddim", 3), ("consistency", 2)):
        assert np.isfinite(pipe.generate("a person walks", seconds=1.6, seed=0, steps=steps, sampler=sampler).joints).all()
    # a teacher is no student to start from
    consistency_toml(cfg, tiny_dataset, wide, steps=2, extra=f'student = "{tiny_model / "denoiser"}"')
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(tmp_path / "run2")]) == 2
    assert "not a consistency-distilled student" in capsys.readouterr().err
