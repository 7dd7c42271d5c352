import json
import re
from pathlib import Path

import numpy as np
import pytest

from conftest import synthetic_walk
from salad.data import build_bvh as bb
from salad.data.build import BuildError
from salad.data.dataset import MotionDataset, read_captions
from salad.motion import representation as rep
from salad.motion.bvh import MIXAMO_MAPPING, bvh_text, save_bvh

TALL = 1.1  # the Mixamo clip's actor is 10% taller


def renamed(text: str, names: dict) -> str:
    """BVH text with the project's joint names replaced."""
    return re.sub(r"^(\s*(?:ROOT|JOINT)\s+)(\S+)", lambda m: m.group(1) + names.get(m.group(2), m.group(2)),
                  text, flags=re.MULTILINE)


@pytest.fixture(scope="module")
def walks():
    return {f"w{i}": synthetic_walk(60 + 8 * i, seed=i, turn=(0.0, 0.6, -0.6, 0.0)[i]) for i in range(4)}


def write_folder(root: Path, walks: dict) -> Path:
    """Four project-named clips with <clip>.txt captions in three line styles, a taller Mixamo-named
    clip in centimetres at 40 fps captioned in captions.json, and three clips that cannot be built."""
    (root / "sub").mkdir(parents=True)
    for name, j in walks.items():
        save_bvh(root / f"{name}.bvh", j)
    (root / "w0.txt").write_text("a person walks forward\n\nsomeone walks ahead\n")
    (root / "w1.txt").write_text("a person turns left while walking#a/DET person/NOUN turn/VERB left/ADV#0#0\n"
                                 "a person takes two steps#1.0#3.0\n")
    (root / "w2.txt").write_text("a person turns right while walking##0.0#0.0\n")
    (root / "w3.txt").write_text("a person walks and waves the left hand\n")
    fast = synthetic_walk(120, seed=9)
    (root / "sub" / "mixamo.bvh").write_text(renamed(bvh_text(fast * TALL, fps=40.0, units="cm"), MIXAMO_MAPPING))
    save_bvh(root / "uncaptioned.bvh", walks["w0"])
    broken = bvh_text(walks["w1"])
    (root / "broken.bvh").write_text(broken[: len(broken) // 2])
    (root / "broken.txt").write_text("a person walks\n")
    (root / "unmapped.bvh").write_text(renamed(bvh_text(walks["w2"]), {"left_wrist": "LeftPalm"}))
    (root / "unmapped.txt").write_text("a person walks\n")
    (root / "captions.json").write_text(json.dumps({"sub/mixamo": ["a tall person walks quickly to the left"]}))
    return fast


def test_build_from_a_folder_of_bvh(tmp_path, walks):
    src, out = tmp_path / "mocap", tmp_path / "hml"
    fast = write_folder(src, walks)
    report = bb.build_bvh(src, out, workers=1, progress=False)

    assert report["clips_found"] == 8 and report["clips_built"] == 5 and report["motions_written"] == 10
    assert sorted(report["skipped"]) == ["broken.bvh", "uncaptioned.bvh", "unmapped.bvh"]
    assert report["uncaptioned"] == ["uncaptioned.bvh"] and "uncaptioned.txt" in report["skipped"]["uncaptioned.bvh"]
    assert str(src / "broken.bvh") in report["skipped"]["broken.bvh"]
    assert "LeftPalm" not in report["skipped"]["unmapped.bvh"] and "left_wrist" in report["skipped"]["unmapped.bvh"]
    assert report["mappings"] == {"salad": 4, "mixamo": 1}
    assert json.loads((out / "build_report.json").read_text()) == report

    ids = sorted(p.stem for p in (out / "new_joint_vecs").glob("*.npy"))
    assert ids == sorted(["w0", "w1", "w2", "w3", "sub_mixamo"] + ["Mw0", "Mw1", "Mw2", "Mw3", "Msub_mixamo"])
    splits = {s: (out / f"{s}.txt").read_text().split() for s in bb.SPLITS}
    assert sorted(sum(splits.values(), [])) == ids
    assert {s: len(v) // 2 for s, v in splits.items()} == report["clips_per_split"] == {"train": 3, "val": 1, "test": 1}
    for s, names in splits.items():
        assert all(("M" + n if not n.startswith("M") else n[1:]) in names for n in names), "mirrors stay with source"
    sources = json.loads((out / "sources.json").read_text())
    assert sources["Msub_mixamo"] == {"source": "sub/mixamo.bvh", "mirrored": True, "mapping": "mixamo",
                                      "split": sources["sub_mixamo"]["split"], "captions_from": "captions.json"}
    assert not (out / "labels.json").exists()

    # captions: all three line styles, mirrored with left and right swapped
    w1 = read_captions(out / "texts" / "w1.txt")
    assert [(c.text, c.start, c.end) for c in w1] == [("a person turns left while walking", 0, 0),
                                                      ("a person takes two steps", 1.0, 3.0)]
    assert w1[0].tokens == "a/DET person/NOUN turn/VERB left/ADV" and "take/VERB" in w1[1].tokens
    assert [c.text for c in read_captions(out / "texts" / "w0.txt")] == ["a person walks forward", "someone walks ahead"]
    assert [c.text for c in read_captions(out / "texts" / "Mw1.txt")][0] == "a person turns right while walking"
    assert "right/ADV" in read_captions(out / "texts" / "Mw1.txt")[0].tokens
    assert read_captions(out / "texts" / "Msub_mixamo.txt")[0].text == "a tall person walks quickly to the right"
    assert read_captions(out / "texts" / "Mw2.txt")[0].text == "a person turns left while walking"

    # the dataset loads; the timestamped caption is its own sub-clip
    items = {it.name: it for s in bb.SPLITS for it in MotionDataset(out, s).items}
    assert len(items) == 12 and len(items["w1@1-3"].features) == len(items["Mw1@1-3"].features) == 40
    assert np.load(out / "Mean.npy").shape == (263,) and (np.load(out / "Std.npy") > 0).all()

    # features -> joints round trip against the input: the 40 fps, centimetre, taller clip comes
    # back at 20 fps on the set's (median) skeleton, so as the original walk's every other frame
    for name, j in [*walks.items(), ("sub_mixamo", fast[::2])]:
        feats = np.load(out / "new_joint_vecs" / f"{name}.npy")
        expected = rep.canonicalize(j.astype(np.float64))[:-1]
        assert feats.shape == (len(j) - 1, 263)
        np.testing.assert_allclose(rep.features_to_joints(feats), expected, atol=1e-4)
        np.testing.assert_allclose(np.load(out / "new_joints" / f"{name}.npy"), expected, atol=1e-4)
    mirrored = rep.features_to_joints(np.load(out / "new_joint_vecs" / "Mw1.npy"))
    np.testing.assert_allclose(mirrored, rep.mirror_joints(rep.canonicalize(walks["w1"].astype(np.float64)))[:-1],
                               atol=1e-4)
    skeleton = json.loads((out / "skeleton.json").read_text())["bone_lengths_m"]
    np.testing.assert_allclose(skeleton, rep.bone_lengths(walks["w0"]), atol=1e-4)


def test_interrupted_build_resumes_and_reruns_are_identical(tmp_path, walks, monkeypatch):
    src = tmp_path / "mocap"
    src.mkdir()
    for name, j in walks.items():
        save_bvh(src / f"{name}.bvh", j)
    (src / "captions.json").write_text(json.dumps({f"{n}.bvh": f"a person walks, take {n}" for n in walks}))
    clean = bb.build_bvh(src, tmp_path / "clean", workers=1, progress=False)

    def crash(*args, **kwargs):
        raise KeyboardInterrupt
    out = tmp_path / "hml"
    with monkeypatch.context() as m:
        m.setattr(bb, "finish_build", crash)
        with pytest.raises(KeyboardInterrupt):
            bb.build_bvh(src, out, workers=1, progress=False)
    assert not out.exists() and (tmp_path / ".hml.building").is_dir()
    report = bb.build_bvh(src, out, workers=1, progress=False)
    assert report["clips_resumed"] == 4 and clean["clips_resumed"] == 0

    def files(d):
        return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*"))
                if p.is_file() and p.name != "build_report.json"}
    assert files(out) == files(tmp_path / "clean")
    bb.build_bvh(src, out, workers=1, progress=False)
    assert files(out) == files(tmp_path / "clean")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clean", "hml", "mocap"]

    # an interrupted build with other settings is not resumed
    with monkeypatch.context() as m:
        m.setattr(bb, "finish_build", crash)
        with pytest.raises(KeyboardInterrupt):
            bb.build_bvh(src, tmp_path / "other", workers=1, progress=False)
    report = bb.build_bvh(src, tmp_path / "other", mirror=False, workers=1, progress=False)
    assert report["clips_resumed"] == 0 and report["motions_written"] == 4
    assert not list((tmp_path / "other" / "new_joint_vecs").glob("M*"))


def test_custom_mapping_file_and_uncaptioned_clips(tmp_path, walks):
    src = tmp_path / "mocap"
    src.mkdir()
    names = {n: f"Bone_{k:02d}" for k, n in enumerate(rep.sk.JOINT_NAMES)}
    for name, j in walks.items():
        (src / f"{name}.bvh").write_text(renamed(bvh_text(j), names))
    (src / "w0.txt").write_text("a person walks\n")
    mapping = tmp_path / "rig.json"
    mapping.write_text(json.dumps(names))
    with pytest.raises(BuildError, match="'salad' lacks pelvis.*pass a mapping"):
        bb.build_bvh(src, tmp_path / "a", workers=1, progress=False)
    report = bb.build_bvh(src, tmp_path / "b", mapping=str(mapping), mirror=False, allow_uncaptioned=True,
                          split=(1.0, 0.0, 0.0), workers=1, progress=False)
    assert report["clips_built"] == 4 and report["mappings"] == {"custom": 4} and report["skipped"] == {}
    assert report["uncaptioned"] == ["w1.bvh", "w2.bvh", "w3.bvh"]
    assert (tmp_path / "b" / "texts" / "w1.txt").read_text() == ""
    assert [it.name for it in MotionDataset(tmp_path / "b", "train").items] == ["w0"]
    # the VAE learns from the uncaptioned clips too
    vae_data = MotionDataset(tmp_path / "b", "train", require_captions=False)
    assert sorted(it.name for it in vae_data.items) == ["w0", "w1", "w2", "w3"]
    assert {it.name: it.captions for it in vae_data.items}["w1"] == [""]
    mapping.write_text(json.dumps({k: v for k, v in names.items() if k != "head"}))
    with pytest.raises(BuildError, match=r"missing \['head'\]"):
        bb.build_bvh(src, tmp_path / "c", mapping=mapping, workers=1, progress=False)


def test_clear_errors(tmp_path, walks):
    src = tmp_path / "mocap"
    out = tmp_path / "out"
    with pytest.raises(BuildError, match="no such folder"):
        bb.build_bvh(src, out)
    src.mkdir()
    (src / "notes.txt").write_text("a person walks\n")
    with pytest.raises(BuildError, match="no .bvh files found"):
        bb.build_bvh(src, out)
    save_bvh(src / "a.bvh", walks["w0"])
    with pytest.raises(BuildError, match=r"none of the 1 BVH files has captions; give each clip captions in <clip>.txt .* captions.json"):
        bb.build_bvh(src, out, progress=False)
    (src / "a.txt").write_text("a person walks\na person#walks\n")
    with pytest.raises(BuildError, match=r"a.txt:2: .*has one '#'"):
        bb.build_bvh(src, out, progress=False)
    (src / "a.txt").write_text("a person walks#3.0#1.0\n")
    with pytest.raises(BuildError, match=r"a.txt:1: timestamps 3..1"):
        bb.build_bvh(src, out, progress=False)
    (src / "a.txt").write_text("a person walks\n")
    (src / "captions.json").write_text(json.dumps({"a.bvh": "a person walks"}))
    with pytest.raises(BuildError, match="keep one"):
        bb.build_bvh(src, out, progress=False)
    (src / "captions.json").write_text(json.dumps({"b.bvh": "a person walks"}))
    with pytest.raises(BuildError, match=r"no BVH file for 1 entries, e.g. \['b.bvh'\]"):
        bb.build_bvh(src, out, progress=False)
    (src / "captions.json").unlink()
    with pytest.raises(BuildError, match="unknown mapping 'maya'"):
        bb.build_bvh(src, out, mapping="maya")
    with pytest.raises(BuildError, match="split fractions"):
        bb.build_bvh(src, out, split=(0.5, 0.1, 0.1))
    with pytest.raises(BuildError, match="replace the input"):
        bb.build_bvh(src, src)
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "thesis.tex").write_text("x")
    with pytest.raises(BuildError, match="not an earlier build"):
        bb.build_bvh(src, tmp_path / "home")
    (src / "a.bvh").write_text("HIERARCHY\nROOT Hips\n{\n")
    with pytest.raises(BuildError, match=rf"no BVH file could be imported; first problems: {re.escape(str(src))}/a.bvh"):
        bb.build_bvh(src, out, workers=1, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["home", "mocap"], "failed builds leave nothing behind"


def test_random_splits_follow_the_fractions_and_are_stable():
    names = [f"clip{i:03d}" for i in range(100)]
    a = bb.random_splits(names, (0.8, 0.05, 0.15), seed=0)
    assert sorted(a.values()).count("train") == 80 and list(a.values()).count("val") == 5
    assert a == bb.random_splits(list(reversed(names)), seed=0)
    assert a != bb.random_splits(names, seed=1)
    b = bb.random_splits(names + ["new"], seed=0)
    assert sum(a[n] != b[n] for n in names) <= 2, "adding a clip moves at most a couple of others"
    assert sorted(bb.random_splits(["x", "y", "z"]).values()) == ["test", "train", "val"]
    assert list(bb.random_splits(["x", "y"]).values()) == ["train", "train"]
    with pytest.raises(BuildError, match="split fractions"):
        bb.random_splits(names, (0.0, 0.5, 0.5))


def test_clip_ids_are_file_safe_and_never_clash_with_mirrors():
    ids = bb._clip_ids(["walks/slow one.bvh", "walks_slow_one.bvh", "Mrun.bvh", "run.bvh", "Move.bvh", ".x.bvh"])
    assert ids["Move.bvh"] == "Move" and ids[".x.bvh"] == "x"
    for rel in ("walks/slow one.bvh", "walks_slow_one.bvh", "Mrun.bvh", "run.bvh"):
        assert re.fullmatch(r"[A-Za-z0-9._-]+-[0-9a-f]{8}", ids[rel]), ids[rel]
    keys = {i.casefold() for i in ids.values()}
    assert len(keys) == len(ids) and not any(("m" + k) in keys for k in keys)
