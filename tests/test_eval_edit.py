"""The editing benchmark: its measures on motions with known answers, and one run end to end."""
import json

import numpy as np
import pytest

from conftest import BANDAI_SUBSET, synthetic_walk
from salad.eval import EMBEDDED_CLASSIFIER
from salad.cli.eval import add_eval_edit as add_parser
from salad.cli.eval import cmd_eval_edit
from salad.eval.edit_bench import judge, regenerate, run_edit_benchmark
from salad.eval.edit_metrics import (body_frame, dominant_wrist, is_monotonic, other_side, pose_distance,
                                     root_trajectory_distance, side_flipped, spearman, timing_correlation)
from salad.eval.edit_suite import DEFAULT_SCALES, default_suite
from salad.eval.edit_suite import MODES as MODES_ALL
from salad.eval.physics import physical_checks
from salad.motion import skeleton as sk
from salad.motion.representation import mirror_features, mirror_joints

WRIST = {"left": sk.JOINT_NAMES.index("left_wrist"), "right": sk.JOINT_NAMES.index("right_wrist")}
ELBOW = {"left": sk.JOINT_NAMES.index("left_elbow"), "right": sk.JOINT_NAMES.index("right_elbow")}


def synthetic_wave(side: str, frames: int = 80, strokes_hz: float = 1.5, amplitude: float = 0.2) -> np.ndarray:
    """Stepping on the spot while one hand is raised and waved sideways."""
    j = synthetic_walk(frames=frames, speed=0.0).astype(np.float64)
    t = np.arange(frames) / 20.0
    sway = amplitude * np.sin(2 * np.pi * strokes_hz * t)
    j[:, WRIST[side]] += np.stack([sway, 0.7 + 0 * t, 0.1 + 0 * t], -1)
    j[:, ELBOW[side]] += np.stack([0.5 * sway, 0.35 + 0 * t, 0.05 + 0 * t], -1)
    return j


def _rotate_y(j: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = j.copy()
    out[..., 0] = c * j[..., 0] + s * j[..., 2]
    out[..., 2] = -s * j[..., 0] + c * j[..., 2]
    return out


# --------------------------------------------------------------------------- measures

def test_mirrored_synthetic_wave_flips_the_leading_wrist():
    for side in ("left", "right"):
        wave = synthetic_wave(side)
        c = physical_checks(wave)
        assert dominant_wrist(c["left_wrist_path_m"], c["right_wrist_path_m"]) == side
        m = physical_checks(mirror_joints(wave))
        assert dominant_wrist(m["left_wrist_path_m"], m["right_wrist_path_m"]) == other_side(side)
        assert m[f"{other_side(side)}_wrist_height_m"] > m[f"{side}_wrist_height_m"] + 0.3
    assert side_flipped("left", "right") and side_flipped("right", "left")
    assert not side_flipped("left", "left") and not side_flipped("none", "none") and not side_flipped("both", "left")
    assert other_side("both") == "both"


def test_identical_motions_preserve_perfectly_and_known_offsets_are_measured():
    walk = synthetic_walk(frames=61, speed=1.2).astype(np.float64)
    assert root_trajectory_distance(walk, walk) == 0.0
    assert timing_correlation(walk, walk) == pytest.approx(1.0)
    for part in ("all", "lower", "upper"):
        assert pose_distance(walk, walk, part) == pytest.approx(0.0, abs=1e-12)
    # slower walk: the gap grows by 0.4 m/s, so its mean over 0..3 s is 0.4 * 1.5 = 0.6 m
    slow = synthetic_walk(frames=61, speed=0.8).astype(np.float64)
    assert root_trajectory_distance(walk, slow) == pytest.approx(0.4 * 1.5, rel=1e-6)
    # the same walk elsewhere and turned: its pose is unchanged, its path is not
    moved = _rotate_y(walk, np.pi / 2) + np.array([3.0, 0.0, -2.0])
    assert pose_distance(moved, walk, "all") < 1e-6
    assert root_trajectory_distance(moved, walk) > 1.0
    assert timing_correlation(moved, walk) == pytest.approx(1.0)
    # the same steps a few frames later: the rhythm no longer lines up, more so the larger the lag
    longer = synthetic_walk(frames=80, speed=1.2).astype(np.float64)
    lags = [timing_correlation(longer[k:k + 61], longer[:61]) for k in (0, 2, 5)]
    assert lags[0] == pytest.approx(1.0) and lags[0] > lags[1] > lags[2] and lags[2] < 0.3


def test_an_arm_edit_leaves_the_lower_body_distance_at_zero():
    wave = synthetic_wave("right")
    still = synthetic_wave("right", amplitude=0.0)
    assert pose_distance(wave, still, "lower") == pytest.approx(0.0, abs=1e-9)
    assert pose_distance(wave, still, "upper") > 0.01
    assert body_frame(wave).shape == wave.shape
    with pytest.raises(ValueError, match="same length"):
        pose_distance(wave, wave[:-4])
    with pytest.raises(ValueError, match="joint set"):
        pose_distance(wave, wave, (3, 40))
    with pytest.raises(ValueError, match="NaN"):
        timing_correlation(wave * np.nan, wave)


def test_spearman_and_monotonic_detection():
    s = DEFAULT_SCALES
    assert spearman(s, [1, 2, 3, 4, 5, 9]) == pytest.approx(1.0)
    assert spearman(s, [6, 5, 4, 3, 2, 1]) == pytest.approx(-1.0)
    assert spearman(s, [1, 1, 1, 1, 1, 1]) == 0.0
    assert is_monotonic([1, 2, 2, 3]) and not is_monotonic([1, 3, 2, 4]) and not is_monotonic([2, 2, 2])
    assert is_monotonic([3, 2, 1], increasing=False)
    with pytest.raises(ValueError):
        spearman([1, 2], [1, 2, 3])


def _described(side: str, joints: np.ndarray) -> dict:
    c = physical_checks(joints)
    return {"content": f"wave-{side}-hand", "style": "normal", "side": side, "checks": c}


def test_judging_a_mirror_edit_needs_both_the_label_and_the_wrist():
    case = next(c for c in default_suite(("mirror",)) if c.name == "wave-left mirror-all")
    src_j = synthetic_wave("left")
    mirrored = mirror_joints(src_j)
    src = _described("left", src_j)
    good = judge(case, src, _described("right", mirrored), mirrored, mirror_joints(src_j))
    assert good["success"] and good["classifier_ok"] and good["physics_ok"] and good["label_kept"]
    assert good["root_dist_m"] == pytest.approx(0.0, abs=1e-9) and good["pose_mpjpe_m"] == pytest.approx(0.0, abs=1e-9)
    # the classifier says "right" but the left hand still leads: not a success
    fake = judge(case, src, _described("right", src_j), src_j, mirror_joints(src_j))
    assert fake["classifier_ok"] and fake["physics_ok"] is False and not fake["success"]
    # the arm moved but the classifier still sees the left hand
    unseen = judge(case, src, _described("left", mirrored), mirrored, mirror_joints(src_j))
    assert not unseen["success"]


def test_side_swaps_must_reach_the_targets_height_and_styles_move_the_readouts():
    swap = next(c for c in default_suite(("swap",)) if c.name == "raise right->left")
    src_j, target_j = synthetic_wave("right"), synthetic_wave("left")
    low = target_j.copy()
    low[:, WRIST["left"], 1] -= 0.3                       # the new hand only gets to head height
    src, target = _described("right", src_j), _described("left", target_j)
    target["content"] = "raise-up-left-hand"
    high = judge(swap, src, target, target_j, src_j, target)
    short = judge(swap, src, {**target, "checks": physical_checks(low)}, low, src_j, target)
    assert high["physics_ok"] and high["success"]
    assert short["classifier_ok"] and short["physics_ok"] is False and not short["success"]
    with pytest.raises(ValueError, match="needs the regenerated target"):
        judge(swap, src, target, target_j, src_j)

    weary = next(c for c in default_suite(("refine",)) if c.name == "walk +wearily")
    walk, slow = synthetic_walk(80, speed=1.2), synthetic_walk(80, speed=0.9)
    base = {"content": "walk", "style": "normal", "side": "none", "checks": physical_checks(walk)}
    tired = {**base, "style": "exhausted", "checks": physical_checks(slow)}
    assert judge(weary, base, tired, slow, walk)["success"]
    assert not judge(weary, base, {**tired, "checks": base["checks"]}, walk, walk)["success"], "as fast as before"
    old = next(c for c in default_suite(("refine",), "held-out") if "elderly" in c.name)
    assert set(old.physics) == {"slower", "leans_forward"}
    bent = slow.copy()
    neck = sk.JOINT_NAMES.index("neck")
    bent[:, neck:, 2] += 0.15 * (bent[:, neck:, 1] > 1.0)     # head, neck and shoulders forward
    stooped = {**tired, "style": "elderly", "checks": physical_checks(bent)}
    assert stooped["checks"]["trunk_lean_deg"] > base["checks"]["trunk_lean_deg"] + 3
    assert judge(old, base, stooped, bent, walk)["physics_ok"]
    assert not judge(old, base, {**stooped, "checks": physical_checks(slow)}, slow, walk)["physics_ok"]


def test_the_held_out_suite_asks_for_every_kind_of_edit_in_other_words():
    tuned, held = default_suite(), default_suite(suite="held-out")
    assert {c.mode for c in held} == set(MODES_ALL) and {c.group for c in held} == {c.group for c in tuned}
    tuned_prompts = {p for c in tuned for p in (c.source, c.target) if p}
    assert not tuned_prompts & {p for c in held for p in (c.source, c.target) if p}
    assert any(c.mode == "reweight" and c.word == "proudly" for c in held)
    with pytest.raises(ValueError, match="unknown edit suite"):
        default_suite(suite="mine")


def test_suite_is_worded_in_the_caption_vocabulary():
    from salad.data.captions import CONTENT_PHRASES, STYLE_PHRASES, caption_variants
    known = {text for content in CONTENT_PHRASES for style in STYLE_PHRASES
             for text, _ in caption_variants(content, style)}
    cases = default_suite() + default_suite(suite="held-out")
    assert {c.mode for c in cases} == {"mirror", "swap", "refine", "reweight"}
    for c in cases:
        for prompt in (c.source, c.target, c.baseline):
            assert prompt is None or prompt in known, prompt
        if c.mode == "swap":
            assert len(c.source.split()) == len(c.target.split())
        if c.mode == "reweight":
            assert c.word in c.source.split()
    with pytest.raises(ValueError, match="unknown edit mode"):
        default_suite(("mirror", "paint"))


@pytest.fixture(scope="module")
def classifier():
    from salad.eval.classifiers import load_classifier
    if not (EMBEDDED_CLASSIFIER / "config.json").is_file():
        pytest.skip(f"{EMBEDDED_CLASSIFIER} is not present")
    return load_classifier(EMBEDDED_CLASSIFIER)


def test_real_classifier_sees_real_captures_flip_under_mirroring(classifier, bandai_subset):
    from salad.motion import joints_to_features
    from salad.motion.bvh import load_bvh
    # a left-hand wave and a right-hand goodbye flip sides; a two-hand raise stays two-handed
    clips = {BANDAI_SUBSET[2]: "left", BANDAI_SUBSET[0]: "right", BANDAI_SUBSET[5]: "both"}
    feats = [joints_to_features(load_bvh(bandai_subset / f"{name}.bvh", fps=20).joints) for name in clips]
    assert classifier.predict(feats)["side"] == list(clips.values())
    mirrored = classifier.predict([mirror_features(f) for f in feats])["side"]
    assert mirrored == [other_side(side) for side in clips.values()]


# --------------------------------------------------------------------------- with a model

@pytest.fixture(scope="module")
def pipe(tiny_model):
    from salad.pipeline import load_pipeline
    pipe = load_pipeline(tiny_model)
    pipe.set_foot_refine(0)   # its L-BFGS through the tiny VAE magnifies the last digits batched and single rows differ in
    return pipe


def test_baselines_start_from_the_edit_noise(pipe):
    prompts, seeds = ["a person walks forward", "a person runs forward"], [3, 11]
    batched = regenerate(pipe, prompts, seeds, frames=32, steps=3)
    for m, p, s in zip(batched, prompts, seeds):
        alone = pipe.generate(p, seconds=1.6, seed=s, steps=3)
        assert m.joints.shape == alone.joints.shape == (32, 22, 3)
        np.testing.assert_allclose(m.joints, alone.joints, atol=1e-4)
    with pytest.raises(ValueError, match="one seed per prompt"):
        regenerate(pipe, prompts, [1], frames=32)


def test_settings_and_classifier_are_checked(pipe, classifier):
    from salad.eval.classifiers import Classifier, ClassifierConfig, MotionClassifier
    from salad.eval.networks import MotionEncoderConfig
    with pytest.raises(ValueError, match="seeds"):
        run_edit_benchmark(pipe, classifier, seeds=0)
    with pytest.raises(ValueError, match="scales"):
        run_edit_benchmark(pipe, classifier, seeds=1, scales=(1.0, 5.0))
    small = ClassifierConfig(motion=MotionEncoderConfig(conv_channels=8, gru_hidden=8, output_dim=8),
                             classes={"content": ["walk", "run"], "style": ["normal"], "side": ["none"]})
    blind = Classifier(MotionClassifier(small), np.zeros(263), np.ones(263))
    with pytest.raises(ValueError, match="needs style class"):
        run_edit_benchmark(pipe, blind, default_suite(("swap",)), seeds=1)


def test_benchmark_end_to_end_on_the_tiny_model(tiny_model, pipe, classifier, tmp_path, capsys):
    import argparse
    p = argparse.ArgumentParser()
    add_parser(p.add_subparsers(dest="command"))
    out = tmp_path / "edit-bench"
    # no planted-feet refinement: its L-BFGS through the tiny VAE magnifies the last float digits in which an
    # edit that replays its recorded source differs from the source (1e-7 m before it, centimetres after)
    a = p.parse_args(["eval-edit", "--model", str(tiny_model), "--classifier", str(EMBEDDED_CLASSIFIER),
                      "--out", str(out), "--seeds", "1", "--steps", "2", "--foot-refine", "0"])
    assert a.func is cmd_eval_edit
    assert a.func(a) == 0
    res = json.loads((out / "results.json").read_text())
    report = (out / "report.md").read_text()
    cases = default_suite()
    assert len(res["records"]) == len(cases)
    assert set(res["summary"]) == {"mirror (all)", "mirror (upper)", "swap: content", "swap: side", "swap: style",
                                   "refine: style"}
    for block in res["summary"].values():
        for method in ("edit", "baseline"):
            assert 0.0 <= block[method]["success"]["mean"] <= 1.0
            assert block[method]["root_dist_m"]["mean"] >= 0.0
            assert -1.0 <= block[method]["timing_corr"]["mean"] <= 1.0
        assert isinstance(block["verdict"]["preserves_more"], bool) and block["verdict"]["text"]
    assert "target_met" in res["summary"]["mirror (all)"]["verdict"]
    # re-weighting by 1 leaves the prompt's maps as they are: the edit reproduces the source
    for name, r in res["reweight"].items():
        assert set(r["amplitude"]) == {f"{s:g}" for s in DEFAULT_SCALES}
        assert r["preservation"]["pose_mpjpe_m"]["1"]["mean"] < 2e-3, name
        assert r["preservation"]["root_dist_m"]["1"]["mean"] < 2e-3, name
        assert 0.0 <= r["within_bounds"]["mean"] <= 1.0
        assert -1.0 <= r["spearman"]["mean"] <= 1.0
    frames = res["settings"]["frames"]
    assert set(frames.values()) == {pipe.frames_for(min(4.0, pipe.max_seconds))}   # one fixed length per case
    assert res["time_s"]["edit_calls"] == 8 + 10 + 5 + 3 * len(DEFAULT_SCALES)
    assert res["settings"]["suite"] == "tuned"
    # the tiny model ships no vocabulary, so "auto" holds nothing; the report says so per case
    assert res["settings"]["held"] == {c.name: None for c in cases}
    assert "| Held to the source |" in report
    for heading in ("## Success and preservation", "## Per case", "## Attention re-weighting", "| mirror (all) |",
                    "Root path distance (m) against the source per scale"):
        assert heading in report
    assert "## Success and preservation" in capsys.readouterr().out
