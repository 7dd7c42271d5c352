import argparse
import contextlib
import math

import numpy as np
import pytest
import torch

from salad.diffusion.guidance import (default_repeats, descend, guided_sample, network_evaluations,
                                      planted_feet_loss, position_loss, refine, step_size)
from salad.diffusion.schedule import NoiseSchedule
from salad.motion.control import (PATH_PRESETS, control_errors, crop_signal, keyframe_signal, lower_body_signal,
                                  make_signal, parse_points, path_signal, preset_path, preset_points, read_keyframes,
                                  read_mola_control, read_motion_joints, read_targets)
from salad.motion.representation import FPS


def test_mola_files_convert_explicitly(shared_data):
    d = shared_data / "mola-control-examples"
    path = read_mola_control(d / "control_example_path_zigzag.npy")
    assert path.joint_mask()[:, 0].all() and path.joint_mask()[:, 1:].sum() == 0
    # the path starts at x = z = 0: still constrained there (a zero is a position, not "free")
    assert path.mask[0, 0].all() and path.targets[0, 0, 0] == 0.0
    se = read_mola_control(d / "control_example_start_end.npy")
    frames = np.flatnonzero(se.joint_mask().any(1))
    assert list(frames) == [0, 1, 2, 3, 96, 97, 98, 99] and se.joint_mask()[frames].all()
    lower = read_mola_control(d / "control_example_lowerbody_circle.npy")
    assert sorted(np.flatnonzero(lower.joint_mask().any(0))) == [0, 1, 2, 4, 5, 7, 8, 10, 11]


def test_mola_file_errors_name_the_file(tmp_path):
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((20, 22, 3), np.float32))
    with pytest.raises(ValueError, match=r"empty\.npy: the mask constrains nothing"):
        read_mola_control(empty)
    nan = tmp_path / "nan.npy"
    a = np.zeros((20, 22, 3), np.float32)
    a[:, 0] = np.nan
    np.save(nan, a)
    with pytest.raises(ValueError, match=r"nan\.npy: contains NaN"):
        read_mola_control(nan)
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.ones((20, 21, 3)))
    with pytest.raises(ValueError, match=r"wrong\.npy: expected .*\(T, 22, 3\), got \(20, 21, 3\)"):
        read_mola_control(wrong)
    pickled = tmp_path / "obj.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"obj\.npy: it holds Python objects"):
        read_mola_control(pickled)
    with pytest.raises(FileNotFoundError, match="missing.npy"):
        read_mola_control(tmp_path / "missing.npy")


def test_signal_builders_and_validation():
    p = path_signal([(0, 0), (0, 2), (1, 3)], frames=40)
    assert p.mask[:, 0, [0, 2]].all() and not p.mask[:, 0, 1].any() and not p.mask[:, 1:].any()
    steps = np.linalg.norm(np.diff(p.targets[:, 0, [0, 2]], axis=0), axis=1)
    assert (~np.isclose(steps, np.median(steps), atol=1e-5)).sum() <= 1, "constant speed (the chord at a corner is shorter)"
    k = keyframe_signal({0: np.zeros((22, 3)) + 0.5, 39: np.ones((22, 3))}, frames=40)
    assert k.joint_mask().sum() == 44
    lb = lower_body_signal(np.random.rand(30, 22, 3))
    assert lb.joint_mask()[:, 20].sum() == 0 and lb.joint_mask()[:, 7].all()
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        make_signal(np.zeros((10, 21, 3)))
    with pytest.raises(ValueError, match="boolean"):
        make_signal(np.zeros((10, 22, 3)), np.zeros((10, 22)))
    with pytest.raises(ValueError, match="constrains nothing"):
        make_signal(np.zeros((10, 22, 3)), np.zeros((10, 22), bool))
    with pytest.raises(ValueError, match="centimetres"):
        make_signal(np.full((10, 22, 3), 150.0))
    free = np.full((10, 22, 3), np.nan)
    free[0, 0] = 1.0
    assert make_signal(free).mask.sum() == 3
    free[1, 1] = np.inf
    with pytest.raises(ValueError, match="infinite"):
        make_signal(free)
    assert crop_signal(k, 20).frames == 20
    with pytest.raises(ValueError, match="constrain nothing"):
        crop_signal(keyframe_signal({30: np.ones((22, 3))}, 40), 20)


@pytest.mark.parametrize("name", PATH_PRESETS)
def test_preset_paths_start_at_the_origin_heading_forward_at_constant_speed(name):
    frames, speed = 101, 1.2
    pts = preset_points(name, frames, speed)
    assert pts.shape == (frames, 2)
    np.testing.assert_allclose(pts[0], 0.0, atol=1e-9)
    step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    np.testing.assert_allclose(step, speed / FPS, rtol=0.02)            # constant speed, one point per frame
    heading = pts[3] - pts[0]
    assert heading[1] > 0 and abs(heading[0]) < 0.3 * heading[1]        # leaves heading +Z, the way motions face
    sig = preset_path(name, frames, speed)
    np.testing.assert_allclose(sig.targets[:, 0, [0, 2]], pts, atol=1e-3)
    assert sig.mask[:, 0, [0, 2]].all() and not sig.mask[:, 0, 1].any()


def test_preset_path_shapes_and_errors():
    left, right = preset_points("turn-left", 100), preset_points("turn-right", 100)
    assert left[-1, 0] > 1.0 and right[-1, 0] < -1.0                   # +X is the character's left
    np.testing.assert_allclose(left * [-1, 1], right, atol=1e-9)
    circle = preset_points("circle", 100)
    assert np.linalg.norm(circle[-1]) < 0.02 and circle[:50, 0].max() > 0.5   # closes, turning left
    line = preset_points("straight", 41, 1.0)                           # the studio's name for it
    np.testing.assert_allclose(line[-1], [0.0, 2.0], atol=1e-9)
    assert preset_path("line", 40, height=0.9).mask[:, 0, 1].all()
    with pytest.raises(ValueError, match="one of line"):
        preset_points("zigzag", 40)
    with pytest.raises(ValueError, match="speed"):
        preset_points("line", 40, speed=-1.0)


def test_studio_presets_are_the_library_presets():
    from app.controls import PRESETS, preset_signal
    from salad.motion.control import PATH_PRESETS, preset_name, preset_polyline

    assert sorted(map(preset_name, PRESETS)) == sorted(PATH_PRESETS)
    for name in PRESETS:
        poly = preset_polyline(name, 3.0)
        assert np.linalg.norm(np.diff(poly, axis=0), axis=1).sum() == pytest.approx(3.0)
        np.testing.assert_allclose(preset_signal(name, 40, 1.2, FPS).targets, preset_path(name, 40, 1.2).targets)
    # at another frame rate the path keeps its speed in metres per second
    slow = preset_signal("straight", 41, 1.0, 10)
    np.testing.assert_allclose(slow.targets[-1, 0, [0, 2]], [0.0, 4.0], atol=1e-6)
    with pytest.raises(ValueError, match="length"):
        preset_polyline("circle", 0.0)


def test_parse_points():
    np.testing.assert_array_equal(parse_points("0,0; 0.5,1.5;0,3"), [[0, 0], [0.5, 1.5], [0, 3]])
    for bad in ("0,0", "0,0;1", "0,0;a,b", "0,0;1,2,3", "0,0;nan,1"):
        with pytest.raises(ValueError, match="path|point"):
            parse_points(bad)


def test_target_keyframe_and_motion_files(tmp_path):
    t = np.full((30, 22, 3), np.nan)
    t[:, 0] = [0.1, 0.9, 0.2]
    np.save(tmp_path / "t.npy", t)
    sig = read_targets(tmp_path / "t.npy")
    assert sig.joint_mask()[:, 0].all() and sig.joint_mask()[:, 1:].sum() == 0
    mask = np.zeros((30, 22), bool)
    mask[5, 3] = True
    np.savez(tmp_path / "t.npz", targets=np.zeros((30, 22, 3)), mask=mask)
    assert read_targets(tmp_path / "t.npz").joint_mask().sum() == 1     # an explicit zero target stays constrained
    np.savez(tmp_path / "bad.npz", positions=np.zeros((30, 22, 3)))
    with pytest.raises(ValueError, match=r"bad\.npz: .*'targets'"):
        read_targets(tmp_path / "bad.npz")
    np.savez(tmp_path / "k.npz", frames=np.array([0, 39]), poses=np.ones((2, 22, 3)))
    k = read_keyframes(tmp_path / "k.npz", frames=40)
    assert list(np.flatnonzero(k.joint_mask().any(1))) == [0, 39]
    with pytest.raises(ValueError, match=r"k\.npz: keyframe 39 is outside"):
        read_keyframes(tmp_path / "k.npz", frames=20)
    with pytest.raises(ValueError, match=r"k\.npz: say how long"):
        read_keyframes(tmp_path / "k.npz")
    np.savez(tmp_path / "k2.npz", frames=np.array([0.5]), poses=np.ones((1, 22, 3)))
    with pytest.raises(ValueError, match="integers"):
        read_keyframes(tmp_path / "k2.npz", frames=20)
    # a saved motion is moved to where generated motions start: origin, facing +Z
    from conftest import synthetic_walk
    walk = synthetic_walk(40)
    turned = walk[..., [2, 1, 0]] * [1, 1, -1] + [3.0, 0.0, -2.0]     # rotated 90 degrees and moved away
    np.save(tmp_path / "m.npy", turned)
    j = read_motion_joints(tmp_path / "m.npy")
    np.testing.assert_allclose(j[0, 0, [0, 2]], 0.0, atol=1e-5)
    np.testing.assert_allclose(j, walk - walk[:1, :1] * [1, 0, 1], atol=1e-3)
    with pytest.raises(ValueError, match=r"m\.txt: expected a motion"):
        read_motion_joints(tmp_path / "m.txt")


def test_control_errors_count_constrained_coordinates_only():
    sig = path_signal([(0, 0), (0, 1)], frames=10)                       # x, z constrained, height free
    j = np.zeros((10, 22, 3))
    j[:, 0, [0, 2]] = sig.targets[:, 0, [0, 2]]
    j[:, 0, 1] = 5.0                                                     # far off in height: not counted
    j[:, 0, 0] += 0.3
    j[:, 5] = 9.0                                                        # unconstrained joint: not counted
    e = control_errors(j, sig)
    assert e.shape == (10,) and np.allclose(e, 0.3)
    assert control_errors(j[:8], sig).shape == (8,)                      # a shorter motion is scored on its frames


@pytest.fixture(scope="module")
def pipe(tiny_model):
    from salad.pipeline import load_pipeline
    return load_pipeline(tiny_model)


def _toy_model(s):
    def model(x, t):          # a "denoiser" that always predicts z0 = 0
        return s.from_x0_eps(torch.zeros_like(x), x / (1 - s.alphas_cumprod[t[0]].float()).sqrt(), t)
    return model


def test_guidance_gradient_points_towards_the_target():
    s = NoiseSchedule()
    target = torch.full((1, 4, 7, 8), 2.0)

    def loss(z0):
        return ((z0 - target) ** 2).sum()

    noise = torch.randn(1, 4, 7, 8, generator=torch.Generator().manual_seed(0))
    plain = guided_sample(_toy_model(s), noise, s, loss, steps=10, strength=0.0, repeats=1)
    kw = dict(steps=10, strength=0.1, repeats=1, refine_steps=0)
    guided = guided_sample(_toy_model(s), noise, s, loss, gradient_steps=1, **kw)
    more = guided_sample(_toy_model(s), noise, s, loss, gradient_steps=2, **kw)
    assert (more - target).abs().mean() < (guided - target).abs().mean() < (plain - target).abs().mean()
    refined = guided_sample(_toy_model(s), noise, s, loss, steps=10, strength=0.1, repeats=1, refine_steps=20)
    assert (refined - target).abs().max() < 1e-3                        # the refinement finishes the job
    assert step_size(500, 1.0) == pytest.approx(1.0) and step_size(0, 1.0) == 0.0
    assert [default_repeats(i, 50) for i in (0, 20, 45)] == [1, 3, 1]
    with pytest.raises(ValueError, match="gradient_steps"):
        guided_sample(_toy_model(s), noise, s, loss, steps=2, gradient_steps=-1)


def test_descend_backtracks_where_a_fixed_step_diverges():
    scales = torch.tensor([1.0, 1000.0])                     # badly conditioned, like integrated root velocities

    def loss(z):
        return (scales * z ** 2).sum()

    z = torch.tensor([1.0, 1.0])
    fixed = z.clone()
    for _ in range(5):
        fixed = fixed - 0.01 * 2 * scales * fixed             # a plain gradient step of 0.01 overshoots
    assert loss(fixed) > loss(z)
    values = [float(loss(z))]
    for _ in range(5):
        z = descend(loss, z, step=0.01)
        values.append(float(loss(z)))
    assert all(b < a for a, b in zip(values, values[1:])) and values[-1] < 1e-2 * values[0]
    many = descend(loss, torch.tensor([1.0, 1.0]), step=0.01, iterations=20)
    assert abs(float(many[1])) < 1e-2 and 0.5 < float(many[0]) < 1.0    # the stiff direction settles, the other crawls
    # the final refinement's quasi-Newton steps solve the same problem outright
    assert float(loss(refine(loss, torch.tensor([1.0, 1.0]), iterations=20))) < 1e-8


def test_position_loss_gradient_moves_joints_towards_targets():
    targets = torch.zeros(6, 22, 3)
    mask = torch.zeros(6, 22, 3, dtype=torch.bool)
    mask[:, 0] = True
    loss = position_loss(lambda z: z.reshape(z.shape[0], 6, 22, 3), targets, mask)
    z = torch.randn(2, 6 * 22 * 3, requires_grad=True)
    g, = torch.autograd.grad(loss(z), z)
    g = g.reshape(2, 6, 22, 3)
    assert (g[:, :, 1:] == 0).all()                                      # unmasked joints get no pull
    moved = z.detach().reshape(2, 6, 22, 3) - 1e-4 * g
    before = z.detach().reshape(2, 6, 22, 3)[:, :, 0].norm()
    assert moved[:, :, 0].norm() < before


def test_planted_feet_loss_stills_planted_feet_and_keeps_the_rest():
    from salad.motion import skeleton as sk
    T = 10
    walk = torch.zeros(1, T, 22, 3)
    walk[..., 2] = torch.arange(T, dtype=torch.float32)[None, :, None] * 0.05      # everything glides 1 m/s forward
    planted = torch.zeros(1, T - 1, 4)
    planted[:, :, :2] = 1.0                                                        # the left foot should stand
    speed2 = planted_feet_loss(lambda j: j, planted, walk, keep_weight=0.0)
    assert float(speed2(walk)) == pytest.approx(1.0, rel=1e-4)                     # (m/s)^2 of the planted joints
    loss = planted_feet_loss(lambda j: j, planted, walk)
    assert float(loss(walk)) == pytest.approx(1.0, rel=1e-4)                       # nothing moved yet
    stood = walk.clone()
    left = list(sk.CONTACT_JOINTS[:2])
    stood[:, :, left] = walk[:, :1, left]
    assert float(speed2(stood)) == 0.0 and 0.0 < float(loss(stood)) < float(loss(walk))
    refined = refine(loss, walk.clone(), iterations=50)
    assert float(speed2(refined)) < 0.1
    others = [j for j in range(22) if j not in left]
    assert torch.allclose(refined[:, :, others], walk[:, :, others], atol=1e-4)    # only what must move moves


def test_time_travel_noise_shared_across_rows_and_model_hook():
    s = NoiseSchedule()
    noise = torch.randn(1, 4, 7, 8, generator=torch.Generator().manual_seed(0)).repeat(2, 1, 1, 1)

    def loss(z0):
        return (z0 ** 2).sum()

    seen = []
    shared = guided_sample(_toy_model(s), noise, s, loss, steps=6, strength=0.1, repeats=3, refine_steps=0,
                           generator=torch.Generator().manual_seed(1), shared_noise=True, before_model=seen.append)
    torch.testing.assert_close(shared[0], shared[1])
    assert seen == [i for i in range(6) for _ in range(3)] and len(seen) == network_evaluations(6, 3)
    apart = guided_sample(_toy_model(s), noise, s, loss, steps=6, strength=0.1, repeats=3, refine_steps=0,
                          generator=torch.Generator().manual_seed(1))
    assert not torch.allclose(apart[0], apart[1])


@contextlib.contextmanager
def deterministic_ddim(pipe):
    """Runs to compare with guided control at strength 0: the deterministic DDIM and plain guidance
    it samples with, no projection (it decodes without), and no feet refinement on either side (guided
    control's keeps its targets, so it would not match a plain one)."""
    kept, projections, refine = (pipe.ddim_eta, pipe.cfg_rescale, pipe.cfg_cutoff), pipe.projections, pipe.foot_refine
    pipe.set_sampling(ddim_eta=0.0, cfg_rescale=0.0, cfg_cutoff=0.0)
    pipe.set_projections(0)
    pipe.set_foot_refine(0)
    try:
        yield pipe
    finally:
        pipe.set_sampling(*kept)
        pipe.set_projections(projections)
        pipe.set_foot_refine(refine)


def test_control_follows_targets_and_leaves_unmasked_joints_free(pipe):
    with deterministic_ddim(pipe):
        free = pipe.generate("a person walks forward", seconds=1.6, seed=5, steps=8)
    targets = free.joints.copy()
    targets[:, 0, 0] += 0.5                       # ask the pelvis to be half a metre to the left
    mask = np.zeros((32, 22), dtype=bool)
    mask[:, 0] = True
    sig = make_signal(targets, mask)
    guided = pipe.control("a person walks forward", signal=sig, seed=5, steps=8, strength=2.0)
    before = np.abs(free.joints[:, 0, 0] - targets[:, 0, 0]).mean()
    after = np.abs(guided.joints[:, 0, 0] - targets[:, 0, 0]).mean()
    assert after < before * 0.8, (before, after)
    assert guided.info["control_mean_error_m"] == pytest.approx(control_errors(guided.joints, sig).mean())
    assert guided.info["control_refine_steps"] == 50           # the teacher's default; the student's is lower
    assert guided.info["projections"] == 0                     # the targets are met through the decoder as is
    assert guided.info["foot_refine"]["evaluations"] in (0, pipe.foot_refine)   # its feet refined, targets kept
    # targets of unmasked joints are ignored entirely: moving them changes nothing
    scrambled = targets.copy()
    scrambled[:, 1:] += np.random.default_rng(0).normal(size=scrambled[:, 1:].shape)
    again = pipe.control("a person walks forward", signal=make_signal(scrambled, mask), seed=5, steps=8,
                         strength=2.0)
    np.testing.assert_array_equal(again.joints, guided.joints)
    # with strength 0 guidance changes nothing at all
    with deterministic_ddim(pipe):
        off = pipe.control("a person walks forward", signal=sig, seed=5, steps=8, strength=0.0, repeats=1)
    np.testing.assert_allclose(off.joints, free.joints, atol=5e-3)
    with pytest.raises(ValueError, match="strength"):
        pipe.control("a person walks", signal=sig, strength=-1)


def test_control_composes_with_attention_editing(pipe):
    from salad.pipeline import EditResult
    prompt = "a person waves their left hand"
    sig = preset_path("line", 32, speed=0.8)
    # without guidance, the composed run is exactly the plain edit
    with deterministic_ddim(pipe):
        plain = pipe.edit(prompt, mode="mirror", mirror="upper", seed=3, seconds=1.6, steps=6)
        off = pipe.control(prompt, signal=sig, seed=3, steps=6, strength=0.0, repeats=1,
                           edit={"mode": "mirror", "mirror": "upper"})
    assert isinstance(off, EditResult)
    np.testing.assert_allclose(off.source.joints, plain.source.joints, atol=5e-3)
    np.testing.assert_allclose(off.edited.joints, plain.edited.joints, atol=5e-3)
    # with guidance and time travel, both branches follow the path and the edit still applies
    res = pipe.control(prompt, signal=sig, seed=3, steps=6, strength=2.0, edit={"mirror": "upper"})
    for guided, free in ((res.source, plain.source), (res.edited, plain.edited)):
        assert control_errors(guided.joints, sig).mean() < 0.8 * control_errors(free.joints, sig).mean()
    assert not np.allclose(res.source.joints, res.edited.joints)
    assert res.params["mirror"] == "upper" and res.params["strength"] == 2.0
    assert res.edited.attention.steps == network_evaluations(6)           # one map per network evaluation
    swapped = pipe.control(prompt, signal=sig, seed=3, steps=4, edit={"target": "a person waves their right hand"})
    assert swapped.params["mode"] == "swap" and swapped.edited.text == "a person waves their right hand"
    with pytest.raises(ValueError, match="unknown edit option"):
        pipe.control(prompt, signal=sig, steps=2, edit={"mirorr": "upper"})
    with pytest.raises(ValueError, match="needs a mode"):
        pipe.control(prompt, signal=sig, steps=2, edit={"tau": 0.5})
    with pytest.raises(ValueError, match="target prompt"):
        pipe.control(prompt, signal=sig, steps=2, edit={"mode": "swap"})


def test_edit_controller_counts_denoising_steps_under_time_travel(pipe, monkeypatch):
    import salad.pipeline
    made = []
    real_build = salad.pipeline.build_edit

    def keep(*args, **kw):
        plan = real_build(*args, **kw)
        made.append(plan.controller)
        return plan
    monkeypatch.setattr(salad.pipeline, "build_edit", keep)
    pipe.control("a person walks forward", signal=preset_path("line", 32), steps=5, repeats=3, edit={"mode": "mirror"})
    counter = made[0].counter
    assert counter.step == 4 and counter.fraction == pytest.approx(0.8)   # not 14: repeats do not advance it


# ---------------------------------------------------------------- the `salad control` command

def _parser():
    from salad.cli.control import add_parser
    p = argparse.ArgumentParser(prog="salad")
    add_parser(p.add_subparsers(dest="command", required=True))
    return p


def test_cli_argument_errors(tmp_path, capsys):
    from salad.cli.control import signal_from_args
    from salad.motion.motion import check_output_paths
    p = _parser()
    with pytest.raises(SystemExit):
        p.parse_args(["control", "a person walks", "-o", "x.npy"])                      # no control source
    with pytest.raises(SystemExit):
        p.parse_args(["control", "a person walks", "--path-preset", "line", "--mola", "f.npy", "-o", "x.npy"])
    assert "not allowed with argument" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        p.parse_args(["control", "a person walks", "--path-preset", "zigzag", "-o", "x.npy"])
    a = p.parse_args(["control", "a person walks", "--path", "0,0;1", "-o", "x.npy"])
    with pytest.raises(ValueError, match="path point 2"):
        signal_from_args(a)
    np.save(tmp_path / "short.npy", np.ones((40, 22, 3), np.float32))
    a = p.parse_args(["control", "a person walks", "--mola", str(tmp_path / "short.npy"), "--seconds", "5",
                      "-o", "x.npy"])
    with pytest.raises(ValueError, match="only 40"):
        signal_from_args(a)
    np.save(tmp_path / "flat.npy", np.ones((40, 66), np.float32))
    a = p.parse_args(["control", "a person walks", "--targets", str(tmp_path / "flat.npy"), "-o", "x.npy"])
    with pytest.raises(ValueError, match=r"flat\.npy: expected targets of shape \(T, 22, 3\)"):
        signal_from_args(a)
    a = p.parse_args(["control", "a person walks", "--path-preset", "circle", "--seconds", "2", "-o", "x.npy"])
    assert signal_from_args(a).frames == 40
    with pytest.raises(ValueError, match="unsupported output type"):
        check_output_paths(["walk.fbx"])


def test_cli_control_writes_the_motion_and_prints_its_error(tiny_model, tmp_path, capsys):
    p = _parser()
    out = tmp_path / "walk.npy"
    a = p.parse_args(["control", "a person walks forward", "--path", "0,0;0.3,1", "--seconds", "1.6", "--steps", "4",
                      "--model", str(tiny_model), "--mirror", "upper", "-o", str(out)])
    assert a.func(a) == 0
    printed = capsys.readouterr().out
    assert "control error: mean" in printed and "source control error" in printed
    assert np.load(out).shape == (32, 22, 3) and np.load(tmp_path / "walk_source.npy").shape == (32, 22, 3)
    mean_cm = float(printed.split("control error: mean ")[1].split(" cm")[0])
    sig = path_signal([(0, 0), (0.3, 1)], 32)
    assert mean_cm == pytest.approx(100 * control_errors(np.load(out), sig).mean(), abs=0.06)
    assert math.isfinite(mean_cm)
