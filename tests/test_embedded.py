"""The shipped model loads by default and makes plausible motions."""
import numpy as np
import pytest

from conftest import BANDAI_SUBSET
from salad.pipeline import EMBEDDED_MODEL, load_pipeline


@pytest.fixture(scope="module")
def pipe():
    if not (EMBEDDED_MODEL / "denoiser").is_dir():
        pytest.fail(f"the embedded model is missing from {EMBEDDED_MODEL}")
    return load_pipeline()


def test_embedded_model_makes_a_plausible_motion_of_the_requested_length(pipe):
    m = pipe.generate("a person walks forward", seconds=3.0, seed=0, steps=20)
    assert m.joints.shape == (60, 22, 3) and m.features.shape == (60, 263)
    assert np.isfinite(m.joints).all()
    feet = m.joints[:, [7, 8, 10, 11], 1]
    assert -0.10 < feet.min() < 0.10, "feet reach the floor"
    height = m.joints[:, 15, 1].mean() - feet.min()
    assert 1.1 < height < 1.8, f"a person-sized skeleton (head {height:.2f} m above the feet)"
    bones = np.linalg.norm(m.joints[:, 18] - m.joints[:, 16], axis=-1)
    assert bones.std() < 0.05, "bone lengths stay put"


def test_embedded_student_is_recorded_fit_for_text_and_guided_control_not_edits(pipe):
    """It meets its bounds on motions from text and guided control, but follows the held-out edits less well than
    the teacher (assets/RESULTS.md, *Session 68*), so the studio's Edit and Real motion panels start on the teacher."""
    assert pipe.student is not None
    assert pipe.student_preferred("control") and pipe.student_preferred("text")
    assert not pipe.student_preferred("edit")


def test_embedded_model_chooses_a_length_itself(pipe):
    m = pipe.generate("a person raises their left hand", seed=1, steps=20)
    assert 16 <= m.frames <= pipe.canvas_frames and m.frames % 4 == 0
    assert np.isfinite(m.joints).all()


def test_auto_length_follows_the_data_for_short_and_long_actions(pipe):
    # in the training data a plain single hand raise lasts ~2 s and a walk with a turn ~5 s; the model's own
    # lengths (its activation channel) and the training data's (the vocabulary's length prior) both say so
    raise_ = pipe.generate("a person raises their right hand", seconds="model", seed=0, steps=20, batch=4)
    walk = pipe.generate("a person walks forward and turns left", seconds="model", seed=0, steps=20, batch=4)
    short, long = np.mean([m.frames for m in raise_]), np.mean([m.frames for m in walk])
    assert short + 20 < long, f"hand raise {short / 20:.1f} s vs walk and turn {long / 20:.1f} s"
    short, long = (pipe.frames_for("prior", p) for p in ("a person raises their right hand",
                                                         "a person walks forward and turns left"))
    assert 28 <= short <= 80 and 80 <= long <= 140 and short + 16 <= long


def test_editing_a_real_walk_keeps_it_a_walk_or_makes_it_a_run(pipe, bandai_subset):
    # The edited branch keeps plain guidance: with the source prompt as its negative prompt the
    # edit was amplified by the CFG scale, so a mirrored walk stood still and a run became a dash.
    walk = str(bandai_subset / f"{BANDAI_SUBSET[1]}.bvh")

    def speed(m):
        return float(np.linalg.norm(m.joints[-1, 0, [0, 2]] - m.joints[0, 0, [0, 2]])) / (m.frames / m.fps)

    mirrored = pipe.edit_real(walk, "a person walks forward", mode="mirror", mirror="all", steps=10, trim=True)
    assert speed(mirrored.source) > 0.5
    # The bug this guards against stopped a mirrored walk (ratio 0.04). Over a 1 s clip the net speed
    # moves with the gait phase: 1 s windows of three test walks mirror to 0.9-1.7x their speed, and this clip
    # to 0.55x (step 17,000) or 0.45x (step 20,000) of it; the bounds leave room for later snapshots while
    # staying five times above the bug.
    assert 0.2 < speed(mirrored.edited) / speed(mirrored.source) < 3.0
    run = pipe.edit_real(walk, "a person walks forward", "a person runs forward", mode="swap", steps=10, trim=True)
    assert speed(run.source) * 1.3 < speed(run.edited) < 6.0      # faster than the walk, slower than a sprint


def test_reweighting_a_word_of_a_standing_action_keeps_its_legs_and_path_by_default(pipe):
    from salad.editing.spec import EditSpec
    from salad.eval.edit_metrics import pose_distance, root_trajectory_distance

    prompt = "a person raises both hands proudly"
    held = pipe.edit(prompt, mode="reweight", reweight={"proudly": -2.0}, seed=0, seconds=4.0, sampler="consistency")
    free = pipe.edit(prompt, mode="reweight", reweight={"proudly": -2.0}, seed=0, seconds=4.0, sampler="consistency",
                     hold=None)
    assert held.params["hold"] == "lower" and free.params["hold"] is None
    # shipped student, seed 0: the path moves 0.03 m held, 0.02-0.04 m free (the edit bench's bound is 0.30 m at
    # every s), too little either way to show the hold; the legs show it: 0.011 m held against 0.064 free
    assert root_trajectory_distance(held.edited.joints, held.source.joints) < 0.1
    held_legs = pose_distance(held.edited.joints, held.source.joints, "lower")
    assert held_legs < 0.03 and held_legs < pose_distance(free.edited.joints, free.source.joints, "lower") / 2
    # the arms are still the edit's: held parts are the legs alone
    assert pose_distance(held.edited.joints, held.source.joints, "upper") > 0.01
    # walking is not an action done in place: its path is what a re-weighted manner word may change
    walk = "a person walks forward slowly"
    assert pipe.resolve_hold(EditSpec(mode="reweight", reweight={"slowly": 2.0}), walk, walk) is None
    assert pipe.resolve_hold(EditSpec(target="a person raises both hands happily"), prompt,
                             "a person raises both hands happily") is None


def test_planted_feet_refinement_stills_a_sliding_walk_at_its_speed(pipe):
    from salad.eval.fidelity import measure
    prompt = "a person walks ahead while veering to the left"      # a held-out paraphrase whose feet slide
    kept = pipe.foot_refine
    try:
        pipe.set_foot_refine(0)
        raw = pipe.generate(prompt, seconds=6.0, seed=0, sampler="consistency", foot_lock=False)
        pipe.set_foot_refine(kept)
        refined = pipe.generate(prompt, seconds=6.0, seed=0, sampler="consistency", foot_lock=False)
        deferred = pipe.generate(prompt, seconds=6.0, seed=0, sampler="consistency", foot_lock=False,
                                 foot_refine=False)
        wave = pipe.generate("a person waves their right hand", seconds=4.0, seed=0, sampler="consistency")
    finally:
        pipe.set_foot_refine(kept)
    # deferred (the studio's preview first): the raw motion now, the refined one from refine_feet
    assert deferred.pending_refinement is not None and "foot_refine" not in deferred.info
    np.testing.assert_allclose(deferred.joints, raw.joints, atol=1e-5)
    later = pipe.refine_feet(deferred)
    assert later.pending_refinement is None
    # the same refinement from the same decoder output, in the same process: what the studio's preview-first
    # path delivers is what generate would have returned
    assert later.info["foot_refine"] == refined.info["foot_refine"]
    np.testing.assert_allclose(later.joints, refined.joints, atol=1e-6)
    assert pipe.refine_feet(later) is later, "refined once"
    before, after = refined.info["foot_refine"]["planted_speed_mps"]
    assert after < 0.6 * before, f"planted feet at {before:.2f} -> {after:.2f} m/s rms"
    a, b = measure(raw.joints), measure(refined.joints)
    assert b["still_foot_share"] >= a["still_foot_share"] + 0.15, (a["still_foot_share"], b["still_foot_share"])
    assert abs(b["root_speed_mps"] - a["root_speed_mps"]) < 0.1 * a["root_speed_mps"], "the walk keeps its pace"
    moved = np.linalg.norm(refined.joints - raw.joints, axis=-1).mean()
    assert moved < 0.06, f"the motion stays itself (joints moved {moved * 100:.1f} cm on average)"
    assert wave.info["foot_refine"]["evaluations"] == 0                # standing feet cost nothing
