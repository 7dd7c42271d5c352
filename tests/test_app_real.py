"""The studio's Real motion tab through its API (gradio_client) on the tiny trained model: an
uploaded BVH or NPY motion or a test clip of a dataset build, inverted and edited by text; bad
uploads; and the tab's pieces (clip library, upload checks, validation, settings) directly."""
from pathlib import Path

import app  # noqa: F401  (switches analytics and hub look-ups off before gradio is imported)
import numpy as np
import pytest
from gradio_client import handle_file
from gradio_client.exceptions import AppError

from salad.data.dataset import read_clip
from salad.motion import representation as rep
from salad.motion.cleanup import clean_motion
from salad.motion.bvh import load_bvh, save_bvh

from app.real_input import ClipLibrary, read_upload, upload_path
from app.settings import MAX_UPLOAD_BYTES, Settings
from app.ui.layout import API_NAMES
from conftest import serve_studio, synthetic_walk

STEPS = 3
SOURCE = "a person walks forward"


@pytest.fixture(scope="module")
def server(pipe, tiny_dataset, tmp_path_factory):
    with serve_studio(pipe, tmp_path_factory.mktemp("studio"), clips=tiny_dataset) as served:
        yield served


@pytest.fixture(scope="module")
def walk_bvh(tmp_path_factory) -> Path:
    """A 3 s synthetic walk written with the project's BVH exporter."""
    path = tmp_path_factory.mktemp("uploads") / "my walk.bvh"
    save_bvh(path, synthetic_walk(61, seed=2), fps=20)
    return path


def edit_real(client, upload=None, clip="", source=SOURCE, mode="mirror", target="", word="", scale=2.0,
              mirror="all", inversion="negative", steps=STEPS, cfg=7.5):
    return client.predict(upload, clip, source, mode, target, word, scale, mirror, inversion, steps, cfg,
                          api_name="/edit_real")


def mp4_frames(path) -> np.ndarray:
    import imageio.v2 as imageio

    with imageio.get_reader(path, format="FFMPEG") as reader:
        return np.stack([frame for frame in reader.iter_data()])


def by_name(files, suffix: str) -> Path:
    return next(Path(f) for f in files if Path(f).name.endswith(suffix))


def component(studio_app, elem_id: str) -> dict:
    return next(c["props"] for c in studio_app.demo.config["components"] if c["props"].get("elem_id") == elem_id)


# ---------------------------------------------------------------- through the API

def test_an_uploaded_bvh_is_inverted_edited_and_rendered_with_its_input(client, pipe, walk_bvh):
    video, summary, files = edit_real(client, upload=handle_file(str(walk_bvh)))
    names = [Path(f).name for f in files]
    assert names == ["my-walk_mirror_side-by-side.mp4", "my-walk_mirror_edited.bvh", "my-walk_mirror_edited_joints.npy",
                     "my-walk_mirror_edited_features.npy"]
    joints, features = np.load(by_name(files, "_edited_joints.npy")), np.load(by_name(files, "_features.npy"))
    n = min(pipe.canvas_frames, 60) // 4 * 4          # 61 frames -> 60 feature frames, cut to the canvas
    assert joints.shape == (n, 22, 3) and joints.dtype == np.float32 and np.isfinite(joints).all()
    assert features.shape == (n, 263) and np.isfinite(features).all()
    # the joints are the features' after the default clean-up (rigid bones, feet pinned)
    np.testing.assert_allclose(clean_motion(rep.features_to_joints(features), features)[0], joints, atol=1e-4)
    again = load_bvh(by_name(files, ".bvh"), fps=20)
    assert again.joints.shape == (n, 22, 3)
    # the BVH reads back as the edited motion, whose bones the clean-up holds at one length
    np.testing.assert_allclose(again.joints, joints, atol=1e-3)
    frames = mp4_frames(video)
    assert frames.shape == (n, 384, 3 * 384, 3) and frames.std() > 5, "input | reconstruction | edit"

    assert "**Mirroring** arms and legs of BVH “my walk\\.bvh” described as “a person walks forward”" in summary
    assert (f"({n} frames, the first of 60 frames)" if n < 60 else f"({n} frames)") in summary
    assert "Reconstruction error (MPJPE)" in summary and "Most changed by the edit" in summary
    assert "Inverted in" in summary and "rendered in" in summary

    # the studio's edit is the pipeline's, on the input as read from the file
    expected = pipe.edit_real(load_bvh(walk_bvh, fps=20).joints, SOURCE, mode="mirror", mirror="all", steps=STEPS,
                              trim=True)
    np.testing.assert_allclose(joints, expected.edited.joints, atol=1e-3)
    mpjpe_cm = float(summary.split("(MPJPE): ")[1].split(" cm")[0])
    assert mpjpe_cm == pytest.approx(100 * expected.source.info["mpjpe_m"], abs=0.06)
    assert np.abs(expected.edited.joints - expected.source.joints).max() > 1e-5, "the edit changed the motion"


def test_npy_joints_and_features_upload_with_every_mode(client, tmp_path):
    walk = synthetic_walk(33, seed=4)
    np.save(tmp_path / "joints.npy", walk.astype(np.float64))
    np.save(tmp_path / "features.npy", rep.joints_to_features(rep.canonicalize(walk.astype(np.float64))))
    cases = [
        (dict(upload="joints.npy", mode="swap", target="a person runs forward"),
         ["**Word swap** to “a person runs forward”", "joints “joints\\.npy”"]),
        (dict(upload="features.npy", mode="refine", target="a person walks forward slowly", inversion="ddim"),
         ["Refinement", "features “features\\.npy”", "plain DDIM inversion"]),
        (dict(upload="features.npy", mode="reweight", word="walks", scale=-1.0, mirror="lower"),
         ["**Re-weighting** “walks” × -1 · mirrored the legs"]),
    ]
    for kwargs, expect in cases:
        kwargs["upload"] = handle_file(str(tmp_path / kwargs["upload"]))
        video, summary, files = edit_real(client, **kwargs)
        for text in expect:
            assert text in summary, (text, summary)
        joints = np.load(by_name(files, "_edited_joints.npy"))
        assert len(joints) == 32 and np.isfinite(joints).all()
        assert mp4_frames(video).shape == (32, 384, 1152, 3)


def test_a_picked_test_clip_prefills_its_caption_and_is_edited(client, server, pipe, tiny_dataset):
    picker = component(server[1], "real-clip")
    assert picker["visible"] and not component(server[1], "real-clips-hint")["visible"]
    tests = (tiny_dataset / "test.txt").read_text().split()
    features, caption = read_clip(tiny_dataset, tests[0], pipe.canvas_frames)
    assert [c[1] for c in picker["choices"]] == [""] + tests
    assert picker["choices"][1][0] == f"{tests[0]}: {caption}"

    source, upload = client.predict(tests[0], api_name="/real_clip")
    assert source == caption and upload is None
    video, summary, files = edit_real(client, clip=tests[0], source=source, mode="reweight", word="walks",
                                      mirror="none")
    assert f"test clip “{tests[0]}” described as “{caption}”" in summary.replace("\\", "")
    joints = np.load(by_name(files, "_edited_joints.npy"))
    n = len(features) // 4 * 4
    assert joints.shape == (n, 22, 3) and np.isfinite(joints).all()
    expected = pipe.edit_real(features, caption, mode="reweight", reweight={"walks": 2.0}, steps=STEPS)
    np.testing.assert_allclose(joints, expected.edited.joints, atol=1e-3)
    assert mp4_frames(video).shape[:3] == (n, 384, 1152)


def test_bad_uploads_and_requests_are_reported_and_the_server_keeps_working(client, tmp_path, walk_bvh):
    (tmp_path / "garbage.bvh").write_bytes(np.random.default_rng(0).bytes(5000).replace(b"\0", b"x"))
    (tmp_path / "binary.bvh").write_bytes(b"\0\1\2" * 100)
    (tmp_path / "cut.bvh").write_text(walk_bvh.read_text().split("MOTION")[0])
    np.save(tmp_path / "wrong.npy", np.zeros((30, 5)))
    np.save(tmp_path / "short.npy", synthetic_walk(10))
    np.save(tmp_path / "nan.npy", np.full((30, 263), np.nan))
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    (tmp_path / "notes.txt").write_text("a walk")
    (tmp_path / "big.npy").write_bytes(b"\x93NUMPY" + bytes(MAX_UPLOAD_BYTES))
    up = lambda name: handle_file(str(tmp_path / name))  # noqa: E731
    cases = [
        (dict(upload=up("garbage.bvh")), "garbage.bvh: not a readable BVH file"),
        (dict(upload=up("binary.bvh")), r"binary.bvh: not a readable BVH file \(not a BVH file \(binary data\)\)"),
        (dict(upload=up("cut.bvh")), "cut.bvh: not a readable BVH file"),
        (dict(upload=up("wrong.npy")), r"wrong.npy: expected joints \(T, 22, 3\) in metres or HumanML3D features "
                                       r"\(T, 263\), got shape \(30, 5\)"),
        (dict(upload=up("short.npy")), "short.npy: 10 frames .* is too short"),
        (dict(upload=up("nan.npy")), "nan.npy: contains NaN or infinite values"),
        (dict(upload=up("objects.npy")), "objects.npy: it holds Python objects, which are not read"),
        (dict(upload=up("notes.txt")), r"notes.txt: expected a BVH file \(.bvh\) or a NumPy array \(.npy\)"),
        (dict(upload=up("big.npy")), "big.npy: 4.0 MB is more than the 4 MB"),
        (dict(), "upload a motion .* or pick a test clip"),
        (dict(upload=handle_file(str(walk_bvh)), clip="000010"), "either an uploaded motion or a test clip, not both"),
        (dict(clip="../../etc/passwd"), "is not one of the offered test clips"),
        (dict(upload=handle_file(str(walk_bvh)), inversion="magic"),
         "inversion must be one of ddim, negative, null_text, fixed_point"),
        (dict(upload=handle_file(str(walk_bvh)), mode="swap", target=""), "word swap needs a target prompt"),
        (dict(upload=handle_file(str(walk_bvh)), mode="reweight"), "choose the word to re-weight"),
        (dict(upload=handle_file(str(walk_bvh)), steps=0), "steps must be between 1 and 200"),
        (dict(upload=handle_file(str(walk_bvh)), source=""), "source prompt is empty"),
    ]
    for kwargs, message in cases:
        with pytest.raises(AppError, match=message):
            edit_real(client, **kwargs)
        if "upload" in kwargs and "clip" not in kwargs and len(kwargs) == 1:
            # the same file is refused the moment it is uploaded, with the same message
            with pytest.raises(AppError, match=message):
                client.predict(kwargs["upload"], api_name="/real_upload")
    # server paths in place of an upload are refused
    for upload in (str(walk_bvh), {"path": "/etc/passwd", "orig_name": "passwd.bvh"}):
        with pytest.raises(AppError):
            edit_real(client, upload=upload)
    assert client.predict(handle_file(str(walk_bvh)), api_name="/real_upload") == "", "a good file is taken"
    _, summary, _ = edit_real(client, upload=handle_file(str(walk_bvh)), mirror="upper")
    assert "**Mirroring** the arms" in summary, "the server still serves"


def test_mode_changes_show_the_controls_the_mode_uses(client):
    help_text, target, mirror, word = client.predict("swap", "all", SOURCE, "", "", api_name="/real_mode")
    assert "Replace words" in help_text and target["visible"] is True and mirror["value"] == "all"
    help_text, target, mirror, word = client.predict("reweight", "none", SOURCE, "", "", api_name="/real_mode")
    assert target["visible"] is False and word["value"] == "forward"
    assert client.predict(None, api_name="/real_upload") == ""


def test_every_real_event_has_an_api_name(server):
    names = {fn.api_name for fn in server[1].demo.fns.values()}
    real_events = {"edit_real", "real_mode", "real_words", "real_clip", "real_upload"}
    assert real_events <= names and real_events <= set(API_NAMES)
    real = next(fn for fn in server[1].demo.fns.values() if fn.api_name == "edit_real")
    assert real.concurrency_id == "model", "real edits queue with every other sampling"


# ---------------------------------------------------------------- the pieces

def test_without_clips_the_picker_is_hidden_and_the_tab_says_how_to_get_some(pipe, tmp_path):
    from app.studio import Studio
    from app.ui.layout import build_studio
    from app.workspace import Workspace

    ws = Workspace(tmp_path)
    try:
        demo = build_studio(Studio(pipe, ws), Settings(tmp_dir=tmp_path))
        props = {c["props"].get("elem_id"): c["props"] for c in demo.config["components"]}
        assert props["real-clip"]["visible"] is False
        assert props["real-clips-hint"]["visible"] is not False
        hint = props["real-clips-hint"]["value"]
        assert "--clips DIR" in hint and "salad data build" in hint
    finally:
        ws.close()


def test_clip_library_spreads_over_the_test_split_and_reads_clips(tiny_dataset, tmp_path):
    lib = ClipLibrary(tiny_dataset)
    tests = (tiny_dataset / "test.txt").read_text().split()
    assert list(lib.clips) == tests and len(lib) == 2
    features = lib.read(tests[1], 24)
    assert features.kind == "clip" and features.motion.shape == (24, 263) and features.shown.shape == (24, 22, 3)
    assert features.caption == lib.caption(tests[1])
    with pytest.raises(ValueError, match="is not one of the offered test clips"):
        lib.read("../train", 24)
    # more clips than offered: spread evenly, first and last kept
    (tmp_path / "texts").mkdir()
    (tmp_path / "new_joint_vecs").mkdir()
    names = [f"{i:03d}" for i in range(9)]
    for name in names:
        (tmp_path / "texts" / f"{name}.txt").write_text(f"a person waves {name}#a/DET#0.0#0.0\n")
        np.save(tmp_path / "new_joint_vecs" / f"{name}.npy", np.zeros((20, 263), np.float32))
    (tmp_path / "test.txt").write_text("\n".join(reversed(names)) + "\n")
    assert list(ClipLibrary(tmp_path, limit=3).clips) == ["000", "004", "008"]
    assert ClipLibrary(tmp_path, limit=3).choices()[1] == ("004: a person waves 004", "004")


def test_uploads_are_checked_before_they_are_read(tmp_path):
    root = tmp_path / "cache"
    root.mkdir()
    save_bvh(root / "walk.bvh", synthetic_walk(30), fps=20)
    up = upload_path({"path": str(root / "walk.bvh"), "orig_name": "../My Walk?.bvh"}, root)
    path, name = up.path, up.name
    assert name == "My Walk_.bvh" and path == (root / "walk.bvh").resolve() and len(up.digest) == 64
    motion = read_upload(path, name)
    assert motion.kind == "bvh" and motion.shown.shape == (30, 22, 3) and motion.motion is motion.shown
    assert np.abs(motion.shown - synthetic_walk(30)).max() < 1e-4     # our exports are in cm, read as metres
    assert upload_path(None, root) is None and upload_path([], root) is None
    save_bvh(tmp_path / "outside.bvh", synthetic_walk(30), fps=20)
    with pytest.raises(ValueError, match="outside.bvh: the upload was not found on the server"):
        upload_path(str(tmp_path / "outside.bvh"), root)
    with pytest.raises(ValueError, match="the upload must be one file"):
        upload_path(42, root)


def test_clips_setting_and_command_line(tiny_dataset, tmp_path):
    from app.cli import parse_args
    from app.settings import DEFAULT_CLIPS, default_clips

    assert parse_args(["--clips", str(tiny_dataset)]).clips == tiny_dataset
    assert parse_args(["--no-clips"]).clips is None
    assert parse_args([]).clips == default_clips()
    assert default_clips() in (None, DEFAULT_CLIPS)
    with pytest.raises(ValueError, match="not a dataset build .*lacks new_joint_vecs, texts, test.txt"):
        Settings(clips=tmp_path)


def test_a_repeated_real_edit_is_answered_from_the_session(pipe, walk_bvh, tmp_path):
    import dataclasses

    from app import real_edit
    from app.studio import Studio
    from app.validation import parse_real_edit
    from app.workspace import Workspace

    studio = Studio(pipe, Workspace(tmp_path))
    session = studio.session(None, "tab-1")
    root = studio.workspace.gradio_cache
    root.mkdir(parents=True, exist_ok=True)
    upload = root / "walk.bvh"
    upload.write_bytes(walk_bvh.read_bytes())
    req, motion = parse_real_edit(pipe, str(upload), "", SOURCE, "mirror", "", "", 2.0, "all", "negative", STEPS, 7.5,
                                  upload_root=root)
    first = real_edit.edit_real(studio, session, req, motion)
    again = real_edit.edit_real(studio, session, req, motion)
    assert again is first and first.reused == 1 and first.intact()
    assert session.latest("real") is first and first.kind == "real" and first.given is motion
    # the same file name with other content is another request
    other = dataclasses.replace(req, input_digest="0" * 64)
    second = real_edit.edit_real(studio, session, other, motion)
    assert second is not first and session.latest("real") is second
