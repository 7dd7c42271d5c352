import numpy as np
import pytest
import torch

from salad.motion import representation as rep
from salad.motion import skeleton as sk
from tests.conftest import synthetic_walk


def test_skeleton_tables_are_consistent():
    assert len(sk.JOINT_NAMES) == 22 and sk.PARENTS[0] == -1
    for level, groups, n_fine in ((sk.JOINTS_12, sk.POOL_22_TO_12, 22), (sk.BODY_PARTS, sk.POOL_12_TO_7, 12)):
        assert len(groups) == level.size
        assert set(j for g in groups for j in g) == set(range(n_fine)), "every fine joint is pooled"
    for level in sk.LEVELS:
        perm = level.mirror_index()
        assert (perm[perm] == np.arange(level.size)).all()
        adj = level.adjacency()
        assert (adj == adj.T).all() and (np.diag(adj) == 1).all()
        # mirroring is a graph automorphism
        assert (adj[np.ix_(perm, perm)] == adj).all()
    pool = sk.pooling_matrix(sk.POOL_22_TO_12, 22)
    np.testing.assert_allclose(pool.sum(1), 1.0)
    unpool = sk.unpooling_matrix(sk.POOL_22_TO_12, 22)
    np.testing.assert_allclose(unpool.sum(1), 1.0)
    # Body-part mirroring agrees with joint mirroring.
    part = sk.PART_OF_JOINT
    assert (sk.BODY_PARTS.mirror_index()[part] == part[sk.JOINTS_22.mirror_index()]).all()


def test_ground_truth_features_to_joints(hml_sample):
    joints = rep.features_to_joints(hml_sample["features"])
    assert joints.shape == hml_sample["joints"].shape
    assert np.abs(joints - hml_sample["joints"]).max() < 1e-4


def test_ground_truth_joints_to_features(hml_sample):
    """Positions, velocities and contacts reproduce the released vector. The facing
    direction is Gaussian-smoothed over time (sigma 20 frames) and the released clip was
    made from one more source frame than new_joints keeps, so the last ~60 frames see a
    slightly different smoothing window: exact far from the end, within 1 cm near it."""
    ref = hml_sample["features"][:-1].astype(np.float64)
    ours = rep.joints_to_features(hml_sample["joints"].astype(np.float64))
    assert ours.shape == ref.shape
    interior = slice(0, ref.shape[0] - 60)
    for name, sl, tol in (("root", slice(0, 4), 1e-5), ("ric", rep.RIC_SLICE, 1e-4),
                          ("rot", rep.ROT_SLICE, 1e-4), ("vel", rep.VEL_SLICE, 1e-5)):
        err = np.abs(ours[interior, sl] - ref[interior, sl]).max()
        assert err < tol, f"{name}: {err}"
    np.testing.assert_array_equal(ours[:, rep.CONTACT_SLICE], ref[:, rep.CONTACT_SLICE])
    assert np.abs(ours[:, rep.RIC_SLICE] - ref[:, rep.RIC_SLICE]).max() < 0.01
    assert np.abs(ours[:, rep.VEL_SLICE] - ref[:, rep.VEL_SLICE]).max() < 1e-3


def test_round_trip_synthetic_and_batched_torch():
    walk = synthetic_walk(80, turn=0.5)
    canon = rep.canonicalize(walk)
    assert abs(canon[..., 1].min()) < 1e-6
    np.testing.assert_allclose(canon[0, 0, [0, 2]], 0.0, atol=1e-6)
    feats = rep.joints_to_features(canon)
    back = rep.features_to_joints(feats)
    # The root's frame-0 facing is the reference: canonicalised motion comes back as it was.
    assert np.abs(back - canon[:-1]).max() < 2e-3
    batch = torch.from_numpy(np.stack([canon, rep.mirror_joints(canon)]))
    fb = rep.joints_to_features(batch)
    assert isinstance(fb, torch.Tensor) and fb.shape == (2, 79, 263)
    np.testing.assert_allclose(fb[0].numpy(), feats, atol=1e-5)


def test_mirroring_features_and_joints_agree():
    walk = rep.canonicalize(synthetic_walk(50, turn=0.7).astype(np.float64))
    f = rep.joints_to_features(walk)
    fm = rep.joints_to_features(rep.mirror_joints(walk))
    np.testing.assert_allclose(rep.mirror_features(f), fm, atol=1e-9)
    np.testing.assert_allclose(rep.mirror_features(rep.mirror_features(f)), f)
    # A left turn mirrors into a right turn.
    assert np.sign(f[:, 0].sum()) == -np.sign(fm[:, 0].sum())


def test_joint_split_is_exact_inverse():
    f = torch.randn(3, 10, 263)
    parts = rep.split_by_joint(f)
    dims = [p.shape[-1] for p in parts]
    assert dims[0] == 7 and dims.count(13) == 4 and dims.count(12) == 17
    assert torch.equal(rep.merge_joints(parts), f)


def test_normalizer_round_trip_and_validation():
    f = np.random.default_rng(0).normal(size=(100, 263)).astype(np.float32)
    mean, std = rep.feature_statistics(f)
    n = rep.Normalizer(mean, std)
    np.testing.assert_allclose(n.denormalize(n.normalize(f)), f, atol=1e-5)
    t = torch.from_numpy(f)
    torch.testing.assert_close(n.normalize(t), torch.from_numpy(n.normalize(f)))
    with pytest.raises(ValueError):
        rep.Normalizer(mean, -std)


def test_bad_shapes_give_clear_errors():
    with pytest.raises(ValueError, match=r"\(\.\.\., T, 22, 3\)"):
        rep.joints_to_features(np.zeros((10, 21, 3)))
    with pytest.raises(ValueError, match="263"):
        rep.features_to_joints(np.zeros((10, 262)))
    with pytest.raises(ValueError, match="at least 2 frames"):
        rep.joints_to_features(np.zeros((1, 22, 3)))
