import numpy as np

from conftest import synthetic_walk
from salad.motion import representation as rep
from salad.motion import skeleton as sk
from salad.motion.bvh import load_bvh
from salad.motion.bvh_export import rest_offsets, rigid_joints, rigid_pose, rigid_positions, save_bvh
from salad.motion.cleanup import clean_motion


def bones(j: np.ndarray) -> np.ndarray:
    return np.linalg.norm(j[:, 1:] - j[:, sk.PARENTS[1:]], axis=-1)          # (T, 21)


def stretched_walk(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A walk through the 263-d representation, then every joint jittered by ~5 mm as the
    decoder's output is (bone lengths change from frame to frame)."""
    f = rep.joints_to_features(rep.canonicalize(synthetic_walk(81, seed=seed).astype(np.float64))).astype(np.float32)
    j = rep.features_to_joints(f)
    noisy = j + np.random.default_rng(seed).normal(0, 0.005, j.shape).astype(np.float32)
    return noisy, f


def test_a_rigid_motion_is_left_as_it_is():
    f = rep.joints_to_features(rep.canonicalize(synthetic_walk(61).astype(np.float64))).astype(np.float32)
    j = rep.features_to_joints(f)
    np.testing.assert_allclose(rigid_joints(j), j, atol=1e-5)


def test_rigid_positions_are_the_posed_rest_skeletons_joints():
    import torch

    noisy, _ = stretched_walk(seed=3)
    j = torch.as_tensor(noisy.astype(np.float64))
    offsets = rest_offsets(j)
    torch.testing.assert_close(rigid_positions(j, offsets), rigid_pose(j, offsets)[1], atol=1e-9, rtol=0)
    # a bone of zero length (the knee on the rigidly placed hip) keeps its parent's rotation: the
    # same answer through rigid_pose's path
    j[5, 5] = rigid_pose(j, offsets)[1][5, 2]
    torch.testing.assert_close(rigid_positions(j, offsets), rigid_pose(j, offsets)[1], atol=1e-9, rtol=0)


def test_clean_up_holds_the_bones_keeps_their_directions_and_exports_exactly(tmp_path):
    noisy, f = stretched_walk()
    assert bones(noisy).std(0).max() > 0.004
    clean, info = clean_motion(noisy, f)
    assert clean.shape == noisy.shape and clean.dtype == noisy.dtype
    assert bones(clean).std(0).max() < 1e-5, "every bone keeps one length"
    # medians (the children of the pelvis and spine3 keep their median placement, not length)
    np.testing.assert_allclose(np.median(bones(clean), 0), np.median(bones(noisy), 0), atol=5e-3)
    # the spine and arms (untouched by the foot lock) keep their bone directions, up to the ~5 mm
    # their parent moved (the pelvis's and spine3's children are fitted together, not one by one)
    for child in (6, 9, 15, 16, 17, 18, 19, 20, 21):
        a = noisy[:, child] - noisy[:, sk.PARENTS[child]]
        b = clean[:, child] - clean[:, sk.PARENTS[child]]
        cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        assert np.median(cos) > 0.99 and cos.min() > 0.9, child      # the head bone is ~10 cm long
    assert 0.0 < info["bones_mean_shift_m"] <= info["bones_max_shift_m"] < 0.1
    assert {"footsteps", "max_shift_m", "unreachable_frames"} <= set(info)
    for units in ("cm", "m"):
        save_bvh(tmp_path / f"w-{units}.bvh", clean, units=units)
        back = load_bvh(tmp_path / f"w-{units}.bvh", fps=20).joints
        assert np.abs(back - clean).max() < 1e-3, units
