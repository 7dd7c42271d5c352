"""Foot locking pins planted feet without breaking the skeleton or making it pop."""
import numpy as np
import pytest

from conftest import synthetic_walk
from salad.eval.physics import still_foot_share
from salad.motion import skeleton as sk
from salad.motion.footlock import LEGS, contact_segments, footsteps, lock_feet, lock_feet_features, two_bone_ik
from salad.motion.representation import foot_contacts

import torch

LEG_BONES = [(hip, knee) for hip, knee, _, _ in LEGS.values()] + [(knee, ankle) for _, knee, ankle, _ in LEGS.values()]


def skating(frames: int = 120, extra: float = 0.5):
    """A synthetic walk whose body travels (1 + extra) times as far as its stride carries it, as a
    skating model's does (planted feet slide at extra × the walking speed), and its true contacts."""
    j = synthetic_walk(frames, seed=0).astype(np.float64)
    c = foot_contacts(torch.from_numpy(j)).numpy()
    c = np.concatenate((c, c[-1:]))                                 # (T, 4), one per frame
    travel = (j[:, :1, :] - j[:1, :1, :]) * np.array([1.0, 0.0, 1.0])
    return j, j + extra * travel, c


def test_locking_holds_planted_toes_still_and_keeps_the_legs_whole():
    _, skated, contacts = skating()
    out, report = lock_feet(skated, contacts)
    assert out.shape == skated.shape and np.isfinite(out).all()
    before, after = still_foot_share(skated), still_foot_share(out)
    assert after > before + 0.2, (before, after)
    assert sum(report.footsteps.values()) >= 4
    # the IK keeps thigh and shin lengths frame by frame
    for a, b in LEG_BONES:
        np.testing.assert_allclose(np.linalg.norm(out[:, a] - out[:, b], axis=-1),
                                   np.linalg.norm(skated[:, a] - skated[:, b], axis=-1), atol=1e-6)
    # nothing above the legs moves sideways; the body may only come down, and by little
    upper = [i for i in range(sk.NUM_JOINTS) if i not in {k for leg in LEGS.values() for k in leg[1:]}]
    np.testing.assert_allclose(out[:, upper][..., [0, 2]], skated[:, upper][..., [0, 2]], atol=1e-9)
    drop = skated[:, upper, 1] - out[:, upper, 1]
    assert drop.min() > -1e-9 and drop.max() <= 0.06 + 1e-9


def test_locking_does_not_pop():
    _, skated, contacts = skating()
    out, _ = lock_feet(skated, contacts)
    step_in = np.linalg.norm(np.diff(skated, axis=0), axis=-1).max()
    step_out = np.linalg.norm(np.diff(out, axis=0), axis=-1).max()
    # a fade over several frames keeps the largest per-frame move near the input's
    assert step_out < step_in + 0.05, (step_in, step_out)


def test_a_still_walk_is_barely_touched_and_no_contact_means_no_change():
    j, _, contacts = skating()
    out, report = lock_feet(j, contacts)
    assert report.max_shift_m < 0.08
    feet = list(sk.CONTACT_JOINTS)
    assert np.abs(out[:, feet] - j[:, feet]).max() < 0.08
    same, none = lock_feet(j, np.zeros_like(contacts))
    np.testing.assert_array_equal(same, j)
    assert none.footsteps == {"left": 0, "right": 0} and none.max_shift_m == 0.0


def test_footsteps_split_a_contact_run_where_the_foot_travels():
    point = np.zeros((12, 3))
    point[6:, 0] = np.linspace(0.0, 1.0, 6)                         # still, then sliding away
    steps = footsteps(point, np.ones(12, dtype=bool), max_drift=0.1)
    assert steps == [(0, 7)]
    assert contact_segments(np.array([1, 0, 1, 1, 0, 1, 1, 1], dtype=bool)) == [(2, 4), (5, 8)]


def test_two_bone_ik_reaches_reachable_targets_and_stretches_toward_the_rest():
    hip = np.array([[0.0, 1.0, 0.0]] * 2)
    knee = np.array([[0.0, 0.55, 0.05]] * 2)
    ankle = np.array([[0.0, 0.1, 0.0]] * 2)
    target = np.array([[0.0, 0.15, 0.2], [0.0, -2.0, 0.0]])
    new_knee, new_ankle, bad = two_bone_ik(hip, knee, ankle, target)
    np.testing.assert_allclose(new_ankle[0], target[0], atol=1e-6)
    assert bad.tolist() == [False, True]
    assert new_ankle[1, 1] < ankle[1, 1]                             # pointing at the far target
    assert new_knee[0, 2] > 0.0                                      # the knee still bends forward


def test_bad_inputs_are_refused():
    j, _, contacts = skating(40)
    with pytest.raises(ValueError, match="joints"):
        lock_feet(j[:, :5], contacts)
    with pytest.raises(ValueError, match="contacts"):
        lock_feet(j, contacts[:10])
    with pytest.raises(ValueError, match="features"):
        lock_feet_features(j, np.zeros((len(j), 3)))
