import numpy as np
import pytest
import torch

from salad.diffusion.guidance import default_repeats, guided_sample, step_size
from salad.diffusion.schedule import NoiseSchedule
from salad.motion.control import keyframe_signal, lower_body_signal, make_signal, path_signal, read_mola_control


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


def test_guidance_gradient_points_towards_the_target():
    s = NoiseSchedule()
    target = torch.full((1, 4, 7, 8), 2.0)

    def loss(z0):
        return ((z0 - target) ** 2).sum()

    def model(x, t):          # a "denoiser" that always predicts z0 = 0
        return s.from_x0_eps(torch.zeros_like(x), x / (1 - s.alphas_cumprod[t[0]].float()).sqrt(), t)

    noise = torch.randn(1, 4, 7, 8, generator=torch.Generator().manual_seed(0))
    plain = guided_sample(model, noise, s, loss, steps=10, strength=0.0, repeats=1)
    guided = guided_sample(model, noise, s, loss, steps=10, strength=0.2, repeats=1)
    assert (guided - target).abs().mean() < (plain - target).abs().mean()
    assert step_size(500, 1.0) == pytest.approx(1.0) and step_size(0, 1.0) == 0.0
    assert [default_repeats(i, 50) for i in (0, 20, 45)] == [1, 3, 1]


def test_control_follows_targets_and_leaves_unmasked_joints_free(tiny_model):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    free = pipe.generate("a person walks forward", seconds=1.6, seed=5, steps=8)
    targets = free.joints.copy()
    targets[:, 0, 0] += 0.5                       # ask the pelvis to be half a metre to the left
    mask = np.zeros((32, 22), dtype=bool)
    mask[:, 0] = True
    sig = make_signal(targets, mask)
    guided = pipe.control("a person walks forward", signal=sig, seed=5, steps=8, strength=20.0)
    before = np.abs(free.joints[:, 0, 0] - targets[:, 0, 0]).mean()
    after = np.abs(guided.joints[:, 0, 0] - targets[:, 0, 0]).mean()
    assert after < before * 0.8, (before, after)
    assert guided.info["control_mean_error_m"] >= 0
    # targets of unmasked joints are ignored entirely: moving them changes nothing
    scrambled = targets.copy()
    scrambled[:, 1:] += np.random.default_rng(0).normal(size=scrambled[:, 1:].shape)
    again = pipe.control("a person walks forward", signal=make_signal(scrambled, mask), seed=5, steps=8,
                         strength=20.0)
    np.testing.assert_array_equal(again.joints, guided.joints)
    # with strength 0 guidance changes nothing at all
    off = pipe.control("a person walks forward", signal=sig, seed=5, steps=8, strength=0.0, repeats=1)
    np.testing.assert_allclose(off.joints, free.joints, atol=5e-3)
    with pytest.raises(ValueError, match="strength"):
        pipe.control("a person walks", signal=sig, strength=-1)
