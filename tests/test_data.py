import json
import re
import tarfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from salad.data import captions as cap
from salad.data.build import (CAPTIONS_PER_CLIP, PLAIN_CAPTIONS, SPLIT_PATTERN, Clip, assign_splits, build_bandai,
                              contrary_turns, cut_off_takes, dataset_stats)
from salad.data.dataset import (DatasetError, MotionDataset, WindowSampler, collate_motions, parse_caption_line)
from salad.motion import representation as rep


def test_every_label_pair_gets_three_varied_captions():
    for content in cap.CONTENT_PHRASES:
        for style in cap.STYLE_PHRASES:
            caps = cap.captions_for(content, style, f"{content}/{style}", 3)
            assert len(set(caps)) == 3
            assert caps == cap.captions_for(content, style, f"{content}/{style}", 3), "reproducible"
    waves = cap.captions_for("wave-left-hand", "exhausted", "x", 12)
    assert len(set(waves)) == 12 and all("left" in c for c in waves)
    adverbs, adjectives = cap.STYLE_PHRASES["exhausted"]
    manner = [m.format(poss=p) for m in adverbs + adjectives for p in ("their", "his", "her")]
    assert all(any(m in c for m in manner) for c in waves), "every caption says the style"
    assert len({c.split(" wave")[0] for c in waves}) > 3, "subjects and word orders vary"


def test_captions_vary_word_order_and_end_frames():
    walks = {c for c, _ in cap.caption_variants("walk", "tired")}
    assert "a man wearily walks forward" in walks and "a man walks forward wearily" in walks
    assert "a man walks forward dragging his feet" in walks
    plain = {c for c, _ in cap.caption_variants("bow", "normal")}
    assert "a person bows and then stops" in plain and "a person bows" in plain


def test_left_right_swapping():
    assert cap.swap_left_right("Left hand, then right; turn counterclockwise") == \
        "Right hand, then left; turn clockwise"
    assert cap.swap_left_right("leftover bright") == "leftover bright"
    assert set(cap.MIRRORED_CONTENT) == {k for k in cap.CONTENT_PHRASES if "left" in k or "right" in k}


def test_crossover_joins_two_captions_at_a_word_they_share():
    rng = np.random.default_rng(0)
    assert cap.crossover("a man kicks with one leg", "a guy waves with his right hand", rng) == \
        "a man kicks with his right hand"
    # neither the first word, an article, nor a cut that gives back a caption: with none left, the first is kept
    assert cap.crossover("a person bows", "a person waves", rng) == "a person bows"
    assert cap.crossover("the man bows low", "a lady waves the hand", rng) == "the man bows low"
    made = {cap.crossover("a man kicks with one leg and then stops", "a guy waves with his hand and then bows", rng)
            for _ in range(40)}
    assert made == {"a man kicks with his hand and then bows", "a man kicks with one leg and then bows"}


def test_caption_lines_parse_back():
    line = cap.caption_line("a person waves their left hand happily")
    c = parse_caption_line(line)
    assert c.text == "a person waves their left hand happily" and c.start == c.end == 0.0
    assert "wave/VERB" in c.tokens
    with pytest.raises(DatasetError):
        parse_caption_line("no fields here")


def test_splits_are_stratified_and_fixed():
    clips = [Clip(f"c{i}_{k}", Path("x"), 2, k, s) for k in ("walk", "run") for s in ("a", "b") for i in range(40)]
    a, b = assign_splits(clips, seed=0), assign_splits(clips, seed=0)
    assert a == b
    for k in ("walk", "run"):
        for s in ("a", "b"):
            counts = Counter(a[c.name] for c in clips if c.content == k and c.style == s)
            assert counts["train"] == 32 and counts["val"] == 2 and counts["test"] == 6
    # an action recorded once still lands in train, wherever the dealing put it
    for offset in range(len(SPLIT_PATTERN)):
        rare = [Clip(f"pad{i}", Path("x"), 1, "bow", "a") for i in range(offset)] + [Clip("k", Path("x"), 1, "kick", "a")]
        assert assign_splits(rare, seed=0)["k"] == "train"


def test_a_dropped_clip_moves_no_other_clip_between_splits():
    clips = [Clip(f"{k}_{s}_{i:03d}", Path("x"), 1, k, s) for k in ("walk", "walk-back") for s in ("normal", "sad")
             for i in range(12)]
    full = assign_splits(clips, seed=0)
    gone = {"walk-back_normal_000", "walk_normal_003"}
    kept = assign_splits(clips, seed=0, dropped=gone)
    assert kept == {n: s for n, s in full.items() if n not in gone}
    # dealing the remaining clips afresh would shift the pattern for every stratum after the first gap
    fresh = assign_splits([c for c in clips if c.name not in gone], seed=0)
    assert fresh != kept
    # a class left with one clip still trains on it, whatever was dropped
    rare = [Clip("k1", Path("x"), 1, "kick", "a"), Clip("k2", Path("x"), 1, "kick", "a")]
    for drop in ({"k1"}, {"k2"}):
        assert list(assign_splits(rare, seed=0, dropped=drop).values()) == ["train"]


def test_a_take_far_shorter_than_its_actions_others_is_cut_off():
    styles = ("normal", "angry", "happy", "old", "sad")
    walks_back = [Clip(f"b1_walk-back_{s}_001", Path(f"{s}.bvh"), 1, "walk-back", s) for s in styles]
    frames = dict(zip((c.name for c in walks_back), (20, 137, 170, 159, 260)))
    cut = cut_off_takes(walks_back, frames)
    assert list(cut) == ["b1_walk-back_normal_001"] and "cut off (20 frames" in cut["b1_walk-back_normal_001"]
    # a short action is judged against its own takes, and three takes are too few for a median
    kicks = [Clip(f"k{i}", Path("k.bvh"), 1, "kick", "normal") for i in range(3)]
    frames.update({"k0": 20, "k1": 200, "k2": 210})
    raises = [Clip(f"r{i}", Path("r.bvh"), 1, "raise", "normal") for i in range(4)]
    frames.update({f"r{i}": 30 + i for i in range(4)})
    assert list(cut_off_takes(walks_back + kicks + raises, frames)) == ["b1_walk-back_normal_001"]


def _turning_body(degrees: float, frames: int = 80) -> np.ndarray:
    """Joints whose hips and shoulders turn by `degrees` about +Y (positive: to the body's left)."""
    from salad.motion import skeleton as sk
    yaw = np.radians(np.linspace(0.0, degrees, frames))
    across = np.stack((np.cos(yaw), np.zeros(frames), -np.sin(yaw)), axis=-1) * 0.1   # the body's left
    j = np.zeros((frames, sk.NUM_JOINTS, 3))
    for name, sign, height in (("left_hip", 1, 0.9), ("right_hip", -1, 0.9),
                               ("left_shoulder", 1, 1.4), ("right_shoulder", -1, 1.4)):
        j[:, sk.JOINT_NAMES.index(name)] = sign * across + [0.0, height, 0.0]
    return j


def test_a_walk_turn_take_that_turns_against_its_action_is_left_out():
    turns = {"l_ok": ("walk-turn-left", 90), "l_wrong": ("walk-turn-left", -90), "r_ok": ("walk-turn-right", -95),
             "r_wrong": ("walk-turn-right", 260), "r_straight": ("walk-turn-right", -10), "walk": ("walk", 120)}
    clips = [Clip(n, Path(f"{n}.bvh"), 2, content, "normal") for n, (content, _) in turns.items()]
    out = contrary_turns(clips, lambda name: _turning_body(turns[name][1]))
    assert sorted(out) == ["l_wrong", "r_straight", "r_wrong"]
    # the ends are averaged over a few smoothed frames, so the angle reads a little under the true turn
    assert re.fullmatch(r"r_wrong.bvh: turns 2[3-6]\d° to the left, against its action walk-turn-right", out["r_wrong"])
    assert re.search(r"turns [5-9]° to the right", out["r_straight"])


def test_loader_batches_windows_and_subclips(tiny_dataset, tmp_path):
    ds = MotionDataset(tiny_dataset, "train")
    assert len(ds) == 8 and ds.dim == 263
    item = ds[0]
    assert item["features"].shape[1] == 263 and isinstance(item["caption"], str)
    batch = collate_motions([ds[i] for i in range(4)])
    assert batch["features"].shape[0] == 4 and batch["features"].shape[1] % 4 == 0
    assert batch["valid"].sum(1).tolist() == batch["lengths"].tolist()
    w = WindowSampler(ds, window=32, overhang=0.5).batch(6, np.random.default_rng(0))
    assert w["features"].shape == (6, 32, 263) and set(np.unique(w["activation"])) <= {0.0, 1.0}
    # a timestamped caption becomes its own sub-clip sample
    import shutil
    d = tmp_path / "ts"
    shutil.copytree(tiny_dataset, d)
    name = (d / "train.txt").read_text().split()[0]
    with open(d / "texts" / f"{name}.txt", "a") as f:
        f.write(cap.caption_line("a person takes two steps", 0.5, 2.5) + "\n")
    ds2 = MotionDataset(d, "train")
    sub = [it for it in ds2.items if it.name.startswith(f"{name}@")]
    assert len(sub) == 1 and len(sub[0].features) == 40 and sub[0].captions == ["a person takes two steps"]
    with pytest.raises(DatasetError, match="new_joint_vecs"):
        MotionDataset(tmp_path / "nothing")


@pytest.mark.shared_data
def test_build_from_real_bandai_clips(bandai_subset, tmp_path):
    archive = tmp_path / "subset.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(bandai_subset, arcname="dataset")
    out = tmp_path / "hml"
    report = build_bandai(archive, out, workers=1, progress=False)
    assert report["clips_found"] == 7 and report["clips_built"] == 5
    assert list(report["skipped"]) == ["b2_walk-turn-right_masculine_007", "b2_wave-left-hand_active_011"]
    assert report["skipped"]["b2_wave-left-hand_active_011"].startswith(
        "subset.tar.xz:dataset/Bandai-Namco-Research-Motiondataset-2/data/dataset-2_wave-left-hand_active_011.bvh: "
        "too short")
    # a take labelled a right turn that turns left is left out, and the right turn that turns right kept
    assert re.search(r"turns \d+° to the left, against its action walk-turn-right",
                     report["skipped"]["b2_walk-turn-right_masculine_007"])
    ids = sorted(p.stem for p in (out / "new_joint_vecs").glob("*.npy"))
    assert len(ids) == 10 and all(f"M{i}" in ids for i in ids if not i.startswith("M"))
    splits = {s: (out / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    assert sorted(sum(splits.values(), [])) == ids
    for s, names in splits.items():  # mirrors stay with their source
        assert {n.lstrip("M") for n in names}.isdisjoint({n.lstrip("M") for t, o in splits.items() if t != s for n in o})
    labels = json.loads((out / "labels.json").read_text())
    assert labels["Mb2_wave-left-hand_active_001"]["content"] == "wave-right-hand"
    mirrored_caps = (out / "texts" / "Mb2_wave-left-hand_active_001.txt").read_text()
    assert "right" in mirrored_caps and "left" not in mirrored_caps
    # bye is captured here in a style only, so a few of its captions name no manner; walk has a normal take
    bye = [parse_caption_line(line).text for line in (out / "texts" / "b1_bye_happy_001.txt").read_text().splitlines()]
    plain = cap.captions_for("bye", "happy", "b1_bye_happy_001/plain", PLAIN_CAPTIONS, plain=True)
    assert len(bye) == CAPTIONS_PER_CLIP and bye[-PLAIN_CAPTIONS:] == plain
    assert not any(w in " ".join(plain) for w in ("happ", "cheer", "joy", "glad", "smil", "merr"))
    walk = [parse_caption_line(line).text for line in (out / "texts" / "b1_walk_normal_002.txt").read_text().splitlines()]
    assert walk == cap.captions_for("walk", "normal", "b1_walk_normal_002", CAPTIONS_PER_CLIP)
    assert np.load(out / "Mean.npy").shape == (263,) and (np.load(out / "Std.npy") > 0).all()
    feats = np.load(out / "new_joint_vecs" / "b2_walk-turn-right_elderly_001.npy")
    joints = np.load(out / "new_joints" / "b2_walk-turn-right_elderly_001.npy")
    np.testing.assert_allclose(rep.features_to_joints(feats), joints, atol=1e-4)
    assert abs(joints[..., 1].min()) < 0.05, "feet on the floor"
    # Channel 0 is the per-frame change of the rotation that turns the facing back to +Z,
    # so a right turn (towards -X) accumulates a positive angle; its mirror a negative one.
    assert np.degrees(2 * feats[:, 0].sum()) > 45
    mirror = np.load(out / "new_joint_vecs" / "Mb2_walk-turn-right_elderly_001.npy")
    assert np.degrees(2 * mirror[:, 0].sum()) < -45
    wave = np.load(out / "new_joints" / "b2_wave-left-hand_active_001.npy")
    left, right = (np.linalg.norm(np.diff(wave[:, w], axis=0), axis=-1).sum() for w in (20, 21))
    assert left > 2 * right, "the left wrist does the waving"
    # A rerun gives the same dataset and leaves nothing behind.
    before = {p.name: p.read_bytes() for p in (out / "new_joint_vecs").iterdir()}
    build_bandai(archive, out, workers=1, progress=False)
    after = {p.name: p.read_bytes() for p in (out / "new_joint_vecs").iterdir()}
    assert before == after
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hml", "subset.tar.xz"]
    stats = dataset_stats(out)
    assert stats["motions"] == 10 and stats["per_content"]["wave-right-hand"] == 1


def test_build_reports_a_bad_source(tmp_path):
    from salad.data.build import BuildError
    with pytest.raises(BuildError, match="no such file"):
        build_bandai(tmp_path / "missing.tar.xz", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BuildError, match="no Bandai"):
        build_bandai(tmp_path / "empty", tmp_path / "out", progress=False)
    bad = tmp_path / "bad.tar.xz"
    bad.write_bytes(b"not an archive")
    with pytest.raises(BuildError, match="cannot read"):
        build_bandai(bad, tmp_path / "out", progress=False)


def test_kit_ml_style_251_dim_directories_load(tmp_path):
    """KIT-ML directories carry 251-d features (21 joints); the loader follows Mean.npy."""
    root = tmp_path / "kit"
    (root / "new_joint_vecs").mkdir(parents=True)
    (root / "texts").mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        np.save(root / "new_joint_vecs" / f"{i:05d}.npy", rng.normal(size=(50 + 10 * i, 251)).astype(np.float32))
        (root / "texts" / f"{i:05d}.txt").write_text(cap.caption_line("a person jumps") + "\n")
    (root / "train.txt").write_text("00000\n00001\n00002\n")
    np.save(root / "Mean.npy", np.zeros(251, np.float32))
    np.save(root / "Std.npy", np.ones(251, np.float32))
    ds = MotionDataset(root, "train")
    assert ds.dim == 251 and len(ds) == 3
    assert collate_motions([ds[0], ds[2]])["features"].shape == (2, 68, 251)
    np.save(root / "new_joint_vecs" / "00001.npy", np.zeros((50, 263), np.float32))
    with pytest.raises(DatasetError, match="251"):
        MotionDataset(root, "train")
