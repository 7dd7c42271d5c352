"""End to end on a tiny model trained here: VAE -> denoiser -> load_pipeline -> generate."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from salad.checkpoint import CheckpointError
from salad.pipeline import end_of_motion, load_pipeline

REPO = Path(__file__).resolve().parents[1]


def test_generate_fixed_and_auto_length(tiny_model):
    pipe = load_pipeline(tiny_model)
    m = pipe.generate("a person walks forward", seconds=1.2, seed=3, steps=5)
    assert m.joints.shape == (24, 22, 3) and m.features.shape == (24, 263)
    assert np.isfinite(m.joints).all()
    again = pipe.generate("a person walks forward", seconds=1.2, seed=3, steps=5)
    assert np.array_equal(m.joints, again.joints), "same seed, same motion"
    other = pipe.generate("a person walks forward", seconds=1.2, seed=4, steps=5)
    assert not np.array_equal(m.joints, other.joints)
    auto = pipe.generate("someone turns left while walking", seed=0, steps=4, sampler="dpm")
    assert 16 <= auto.frames <= pipe.canvas_frames and auto.frames % 4 == 0
    many = pipe.generate("a person walks forward", seconds=1.0, steps=3, batch=3)
    assert len(many) == 3 and not np.array_equal(many[0].joints, many[1].joints)


def test_generate_with_attention(tiny_model):
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)        # its line search would magnify the last digits the two attention paths differ in
    m = pipe.generate("a person waves their left hand", seconds=1.6, steps=4, return_attention=True)
    att = m.attention
    assert att.words == ["a", "person", "waves", "their", "left", "hand"]
    agg = att.aggregate()
    assert agg.shape == (6, 7, 32)
    assert att.data.shape[:2] == (4, 3)           # steps x layers
    assert np.isfinite(agg).all() and (agg >= 0).all()
    assert att.word("left", layers=[0], steps=(2, 4)).shape == (7, 32)
    # attention is off again afterwards: fused path, same result as a plain call
    plain = pipe.generate("a person waves their left hand", seconds=1.6, steps=4)
    np.testing.assert_allclose(plain.joints, m.joints, atol=2e-3)  # bf16: fused vs explicit softmax


def test_bad_inputs_are_rejected_clearly(tiny_model):
    pipe = load_pipeline(tiny_model)
    for kwargs, msg in (({"prompt": "   "}, "empty"), ({"prompt": "x" * 400}, "limit"),
                        ({"prompt": "walk", "seconds": 0.1}, "between"), ({"prompt": "walk", "seconds": "soon"}, "number"),
                        ({"prompt": "walk", "steps": 0}, "steps"), ({"prompt": "walk", "cfg": float("nan")}, "cfg"),
                        ({"prompt": "walk", "sampler": "euler"}, "sampler"), ({"prompt": "walk", "batch": 0}, "batch"),
                        ({"prompt": "walk", "seed": -1}, "seed"), ({"prompt": "walk", "seed": 2**70}, "seed"),
                        ({"prompt": "walk", "seed": 1.5}, "seed")):
        with pytest.raises(ValueError, match=msg):
            pipe.generate(**kwargs)
    for call in (lambda: pipe.edit("walk", "run", seed=-1), lambda: pipe.generate_batch(["walk"], [20], seed=-1),
                 lambda: pipe.control("walk", targets=np.zeros((20, 22, 3)), seed=-1)):
        with pytest.raises(ValueError, match=r"seed must be an integer in 0\.\."):
            call()
    assert pipe.generate("walk", seconds=1.0, steps=2, seed=np.int64(3)).seed == 3
    with pytest.raises(CheckpointError, match="not found"):
        load_pipeline(tiny_model.parent / "nowhere")


def test_end_of_motion_follows_activation():
    act = np.ones(100)
    act[57:] = 0.1
    assert end_of_motion(act) == 56
    assert end_of_motion(np.ones(40)) == 40
    assert end_of_motion(np.zeros(40)) == 16


def test_cli_generate_writes_files(tiny_model, tmp_path, cli):
    out = subprocess.run([sys.executable, "-m", "salad.cli", "generate", "a person walks forward", "--model",
                          str(tiny_model), "--seconds", "1.0", "--steps", "3", "-o", str(tmp_path / "w.npy"),
                          "-o", str(tmp_path / "w.bvh"), "-o", str(tmp_path / "w.png"), "--bvh-units", "m"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert np.load(tmp_path / "w.npy").shape == (20, 22, 3)
    assert (tmp_path / "w.bvh").read_text().startswith("HIERARCHY")
    from salad.motion.bvh import load_bvh
    assert load_bvh(tmp_path / "w.bvh").scale == 1.0                 # --bvh-units m
    from PIL import Image
    strip = Image.open(tmp_path / "w.png")
    assert strip.height == 256 and strip.width == 6 * 256 + 5 * 2     # six frames with 2-pixel gaps
    # refusals in-process (the same main() as the command; a process start costs seconds)
    code, err = cli("generate", "a person walks", "--model", str(tiny_model), "-o", str(tmp_path / "w2.npy"),
                        "-o", str(tmp_path / "w.fbx"))
    assert code == 2 and "unsupported output type '.fbx'" in err
    assert not (tmp_path / "w2.npy").exists()                       # refused before sampling anything
    code, err = cli("generate", "", "--model", str(tiny_model), "-o", str(tmp_path / "x.npy"))
    assert code == 2 and "empty" in err
    code, err = cli("generate", "a person walks", "--model", str(tiny_model), "--seconds", "100",
                        "-o", str(tmp_path / "x.npy"))
    assert code == 2 and err.startswith("salad: error: seconds must be between")  # no bar before it


def test_generated_motions_can_go_through_the_vae_once_more_before_the_last_decode(tiny_model):
    import torch

    from salad.pipeline import LATENT_PROJECTIONS
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)                 # the projection alone (the refinement after it has its own test)
    plain = pipe.generate("a person walks forward", seconds=1.2, seed=3, steps=3)
    assert plain.info["projections"] == pipe.projections == LATENT_PROJECTIONS == 0
    precision = "bf16 autocast from 2 rows a forward" if pipe.bf16 else "fp32"      # as the machine allows
    assert pipe.sampler_settings("consistency") == {"projections": 0, "foot_refine": 0, "precision": precision}
    pipe.set_projections(1)
    projected = pipe.generate("a person walks forward", seconds=1.2, seed=3, steps=3)
    assert projected.info["projections"] == 1 and not np.allclose(plain.features, projected.features, atol=1e-3)
    assert pipe.sampler_settings("consistency") == {"projections": 1, "foot_refine": 0, "precision": precision}
    # reports say what the model ran in, after the sampling settings
    from salad.diffusion.sampling import describe_settings
    assert describe_settings({"sampler": "consistency", **pipe.sampler_settings("consistency")}) == \
        f" (1 VAE projection, {precision})"
    # one projection: the decoded motion encoded to its posterior mean and decoded again
    with torch.no_grad():
        mu, _ = pipe.vae.encode(torch.from_numpy(pipe.normalizer.normalize(plain.features)).float()[None])
        again = pipe.normalizer.denormalize(pipe.vae.decode(mu)[0][0].numpy())
    assert np.allclose(projected.features, again, atol=1e-3)
    for bad in (-1, 9, 1.5, True, "1"):
        with pytest.raises(ValueError, match="projections must be an integer in 0..8"):
            pipe.set_projections(bad)
    assert pipe.projections == 1


def test_planted_feet_refinement_setting_and_report(tiny_model):
    from salad.pipeline import FOOT_REFINE_EVALUATIONS
    pipe = load_pipeline(tiny_model)
    assert pipe.foot_refine == FOOT_REFINE_EVALUATIONS > 0
    assert pipe.sampler_settings("consistency")["foot_refine"] == FOOT_REFINE_EVALUATIONS
    refined = pipe.generate("a person walks forward", seconds=2.0, seed=3, steps=3, foot_lock=False)
    report = refined.info["foot_refine"]
    before, after = report["planted_speed_mps"]
    assert report["evaluations"] in (0, FOOT_REFINE_EVALUATIONS)
    assert after <= before + 1e-6 and (report["evaluations"] or before == after)
    pipe.set_foot_refine(0)
    plain = pipe.generate("a person walks forward", seconds=2.0, seed=3, steps=3, foot_lock=False)
    assert "foot_refine" not in plain.info
    assert report["evaluations"] == 0 or not np.allclose(plain.features, refined.features, atol=1e-4)
    for bad in (-1, 501, 2.0, True, "20"):
        with pytest.raises(ValueError, match="foot refinement evaluations must be an integer in 0..500"):
            pipe.set_foot_refine(bad)
    assert pipe.foot_refine == 0


def test_generate_batch_with_mixed_lengths(tiny_model):
    pipe = load_pipeline(tiny_model)
    out = pipe.generate_batch(["a person walks forward", "someone turns left while walking"], [24, 36], seed=1,
                              steps=4)
    assert [m.frames for m in out] == [24, 36]
    assert all(np.isfinite(m.joints).all() for m in out)
    with pytest.raises(ValueError, match="multiples of 4"):
        pipe.generate_batch(["a person walks"], [30])


def test_unguided_steps_skip_the_unconditional_rows_with_or_without_controllers(tiny_model):
    from salad.editing.store import AttentionStore

    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)        # its line search would magnify the last digits the two attention paths differ in
    rows = []
    hook = pipe.denoiser.register_forward_hook(lambda module, args, out: rows.append(out.shape[0]))
    walk = dict(seconds=1.6, seed=4, steps=10, foot_lock=False)
    try:
        plain = pipe.generate("a person walks forward", **walk)
        assert rows == [2] * 7 + [1] * 3          # t = 299, 199, 99 are below the 0.3 cutoff
        rows.clear()
        watched = pipe.generate("a person walks forward", return_attention=True, **walk)
        assert rows == [2] * 7 + [1] * 3          # the store is told where the prompt's row went
        rows.clear()
        edit = dict(mode="swap", target_prompt="a person runs forward", **walk)
        replayed = pipe.edit("a person walks forward", **edit)
        assert rows == [2] * 7 + [1] * 3          # the source generated just before is replayed: the edit alone
        assert replayed.edited.info["source_replayed"]
        rows.clear()
        pipe.source_runs.clear()
        edited = pipe.edit("a person walks forward", **edit)
        assert rows == [4] * 7 + [2] * 3          # source + target, their CFG rows above the cutoff
        rows.clear()
        # a controller that reads an unconditional row keeps every row on every step
        text = pipe.sampler_text(["a person walks forward"], "ddim")
        fn = pipe.model_fn(text, auto=False)
        with pipe.denoiser.controlled(AttentionStore(text, rows=slice(0, 2), frames=32)):
            assert not hasattr(pipe.model_fn(text, auto=False), "conditional")
        assert hasattr(fn, "conditional")
    finally:
        hook.remove()
    assert watched.attention is not None and watched.attention.steps == 10
    np.testing.assert_allclose(plain.joints, watched.joints, atol=1e-3)
    # the same edit with every row on every step: the same motions and maps
    shortcut = pipe.model_fn

    def every_row(*args, **kwargs):
        fn = shortcut(*args, **kwargs)
        fn.__dict__.pop("conditional", None)
        return fn
    pipe.model_fn = every_row
    pipe.source_runs.clear()
    reference = pipe.edit("a person walks forward", **edit)
    for got, want in ((edited.source, reference.source), (edited.edited, reference.edited)):
        np.testing.assert_allclose(got.joints, want.joints, atol=1e-3)
        np.testing.assert_allclose(got.attention.aggregate(), want.attention.aggregate(), atol=1e-4)


def test_ancestral_ddim_is_seeded_and_an_edit_source_is_the_plain_generation(tiny_model, cli):
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)        # the edit's branches and the plain source differ in their last digits
    assert (pipe.ddim_eta, pipe.cfg_rescale, pipe.cfg_cutoff) == (1.0, 0.7, 0.3)   # the defaults the model card measures
    walk = dict(seconds=1.6, seed=4, steps=6, foot_lock=False)
    a, b = pipe.generate("a person walks forward", **walk), pipe.generate("a person walks forward", **walk)
    np.testing.assert_array_equal(a.joints, b.joints)                  # a seed still gives one motion
    assert not np.allclose(pipe.generate("a person walks forward", **{**walk, "seed": 5}).joints, a.joints)
    # both edit branches draw the same fresh noise as a plain generation of the source
    res = pipe.edit("a person walks forward", mode="mirror", mirror="all", **walk)
    np.testing.assert_allclose(res.source.joints, a.joints, atol=1e-3)
    pipe.set_projections(0)       # the sampler's own latents: the tiny VAE's projection pulls both to one motion
    a = pipe.generate("a person walks forward", **walk)
    pipe.set_sampling(ddim_eta=0.0, cfg_rescale=0.0)
    assert not np.allclose(pipe.generate("a person walks forward", **walk).joints, a.joints, atol=1e-3)
    for bad in ({"ddim_eta": 1.5}, {"ddim_eta": -0.1}, {"cfg_rescale": float("nan")}, {"cfg_rescale": "high"}):
        with pytest.raises(ValueError, match="must be a number in \\[0, 1\\]"):
            pipe.set_sampling(**bad)
    with pytest.raises(ValueError, match="cfg_cutoff must be a number in \\[0, 0.99\\]"):
        pipe.set_sampling(ddim_eta=1.0, cfg_cutoff=1.0)
    assert (pipe.ddim_eta, pipe.cfg_rescale) == (0.0, 0.0)              # a refused setting changes nothing
    code, err = cli("generate", "a person walks", "--model", str(tiny_model), "--ddim-eta", "2",
                        "-o", "/tmp/never.npy")
    assert code == 2 and "ddim_eta must be a number in [0, 1], got 2.0" in err


def test_sde_dpm_solver_draws_seeded_noise_that_edit_branches_share_and_replays(tiny_model):
    from salad.diffusion.sampling import describe_settings
    pipe = load_pipeline(tiny_model, bf16=False)
    pipe.set_foot_refine(0)
    pipe.set_projections(0)        # the sampler's own latents: the tiny VAE's projection pulls motions together
    walk = dict(seconds=1.6, seed=4, steps=6, foot_lock=False, sampler="dpm-sde")
    a, b = pipe.generate("a person walks forward", **walk), pipe.generate("a person walks forward", **walk)
    np.testing.assert_array_equal(a.joints, b.joints)
    assert not np.allclose(pipe.generate("a person walks forward", **{**walk, "seed": 5}).joints, a.joints, atol=1e-3)
    deterministic = pipe.generate("a person walks forward", **{**walk, "sampler": "dpm"})
    assert not np.allclose(deterministic.joints, a.joints, atol=1e-3), "fresh noise at each step"
    # both edit branches draw the noise a plain generation of the source draws, and a replay of the recorded
    # source (the multistep solver's history kept for the edited rows alone) edits to the same motion
    first = pipe.edit("a person walks forward", mode="mirror", mirror="all", **walk)
    np.testing.assert_allclose(first.source.joints, a.joints, atol=1e-3)
    again = pipe.edit("a person walks forward", mode="mirror", mirror="all", **walk)
    assert again.edited.info["source_replayed"] and not first.edited.info["source_replayed"]
    np.testing.assert_allclose(again.edited.joints, first.edited.joints, atol=1e-4)
    calls = []
    forward = pipe.denoiser.forward
    pipe.denoiser.forward = lambda z, *a, **k: calls.append(z.shape[0]) or forward(z, *a, **k)
    pipe.generate("a person walks forward", seconds=1.6, sampler="dpm-sde")
    assert len(calls) == 25, "its default steps"
    words = describe_settings({"sampler": "dpm-sde", **pipe.sampler_settings("dpm-sde")})
    assert "fresh noise at every step" in words and "eta" not in words


def test_a_sampler_started_part_of_the_way_down_finishes_as_the_whole_run_would(tiny_model):
    import torch
    pipe = load_pipeline(tiny_model)
    pipe.set_sampling(ddim_eta=0.0)                # deterministic steps: the tail must be the same computation
    text = pipe.sampler_text(["a person walks forward"], "ddim")
    noise = pipe.noise(1, 32, seed=3)
    seen = {}
    whole = pipe.denoise(text, noise, "ddim", 10, 7.5, auto=False, on_step=lambda i, n, x: seen.setdefault(i, x))
    tail = pipe.denoise(text, seen[4], "ddim", 10, 7.5, auto=False, start=4)
    torch.testing.assert_close(tail, whole, atol=1e-5, rtol=1e-5)
    for bad in (-1, 10):
        with pytest.raises(ValueError, match="start must be in 0..9"):
            pipe.denoise(text, noise, "ddim", 10, 7.5, auto=False, start=bad)
    with pytest.raises(ValueError, match="only the ddim sampler"):
        pipe.denoise(text, noise, "dpm", 10, 7.5, auto=False, start=2)


def test_compiled_networks_give_the_eager_motions_and_step_aside_for_controllers(tiny_student):
    import torch._dynamo

    pipe = load_pipeline(tiny_student, bf16=False)
    pipe.set_foot_refine(0)        # its line search would magnify the last digits compiled kernels round differently
    with pytest.raises(ValueError, match="cannot compile 'text'"):
        pipe.compile(("denoiser", "text"))
    assert pipe.compiled == {}
    # the teacher's guided steps run 2 rows, its unguided last ones 1, at another length than the student's
    calls = [("a person walks forward", dict(seconds=1.6, steps=3, sampler="consistency")),
             ("a person walks forward", dict(seconds=1.2, steps=4, sampler="ddim"))]
    eager = [pipe.generate(prompt, **kw) for prompt, kw in calls]
    watched = pipe.generate("a person waves", seconds=1.2, steps=2, sampler="consistency", return_attention=True)

    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    pipe.compile()
    assert set(pipe.compiled) == {"denoiser", "student", "decoder"}
    for (prompt, kw), before in zip(calls, eager):
        after = pipe.generate(prompt, **kw)
        assert after.frames == before.frames
        np.testing.assert_allclose(after.joints, before.joints, atol=1e-3)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 3, "the compiled networks did not run"
    # an observed sampling runs the eager modules, whose maps the store reads
    again = pipe.generate("a person waves", seconds=1.2, steps=2, sampler="consistency", return_attention=True)
    np.testing.assert_allclose(again.attention.data, watched.attention.data, atol=1e-4)
    np.testing.assert_allclose(again.joints, watched.joints, atol=1e-3)


def test_the_compile_flag_reaches_the_pipeline(tiny_model):
    from salad.cli import build_parser
    from salad.cli.common import apply_sampling

    parser = build_parser()
    for argv in (["generate", "a person walks", "-o", "w.npy"],
                 ["control", "a person walks", "--path-preset", "circle", "-o", "w.npy"]):
        pipe = load_pipeline(tiny_model)
        apply_sampling(pipe, parser.parse_args(argv))
        assert pipe.compiled == {}
        apply_sampling(pipe, parser.parse_args(argv + ["--compile"]))
        assert set(pipe.compiled) == {"denoiser", "decoder"}          # the tiny model has no student


def test_the_cli_progress_bar_rates_from_its_first_report():
    from salad.cli.common import LazyBar

    bar = LazyBar("sampling")
    bar.update(1, 50)                       # the bar appears at the first step, already one step in
    try:
        assert bar.bar.n == 1 and bar.bar.total == 50
        assert "?it/s" in str(bar.bar)      # no rate from a step that took no time on this bar
        bar.update(2, 64)                   # the length watch can lengthen the run
        assert bar.bar.total == 64 and bar.bar.n == 2
    finally:
        bar.close()
