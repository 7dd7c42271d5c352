"""The studio's Edit and Control tabs through their API (gradio_client) on the tiny trained
model, and their pieces (validation, presets, uploads, keyframes, comparisons) directly."""
import json
from pathlib import Path

import app  # noqa: F401  (switches analytics and hub look-ups off before gradio is imported)
import numpy as np
import pytest
from gradio_client import handle_file
from gradio_client.exceptions import AppError

from salad.motion import skeleton as sk
from salad.motion.control import lower_body_signal, make_signal, preset_polyline

from app.compare import motion_difference
from app.controls import PRESETS, display_name, parse_keyframes, pelvis_path, preset_signal, upload_file
from app.figures import control_top_view
from app.session import Result, Session
from app.settings import MAX_UPLOAD_BYTES, Settings
from app.studio import Studio
from app.validation import ControlRequest, EditRequest, parse_control, parse_edit
from app.workspace import Workspace
from conftest import mp4_frames, serve_studio, synthetic_walk

STEPS = 4
SOURCE = "a person waves their right hand happily"
TARGET = "a person waves their left hand happily"


@pytest.fixture(scope="module")
def examples_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("control-examples")
    a = np.zeros((24, 22, 3), np.float32)
    a[:4] = synthetic_walk(24)[:4]          # MoLA-style in-betweening: first and last frames fixed
    a[-4:] = synthetic_walk(24)[-4:]
    np.save(d / "start_end.npy", a)
    return d


@pytest.fixture(scope="module")
def server(pipe, examples_dir, tmp_path_factory):
    with serve_studio(pipe, tmp_path_factory.mktemp("studio"), control_examples=examples_dir) as served:
        yield served


def edit(client, source=SOURCE, mode="swap", target=TARGET, tau=None, word="", scale=2.0, mirror="none",
         self_inject=0.2, hold="auto", seconds=1.2, seed=0, steps=STEPS, cfg=7.5, sampler="ddim"):
    return client.predict(source, mode, target, tau, word, scale, mirror, self_inject, hold, seconds is None, seconds,
                          seed, steps, cfg, sampler, api_name="/edit")


def control(client, prompt="a person walks forward", task="path", preset="circle", seconds=1.2, speed=1.0,
            upload=None, example="", keyframes="first, last", strength=3.0, seed=0, steps=STEPS, cfg=7.5):
    return client.predict(prompt, task, preset, seconds, speed, upload, example, keyframes, strength, seed, steps, cfg,
                          api_name="/control")


def plot(value) -> dict:
    return json.loads(value["plot"])


def by_name(files, suffix: str) -> Path:
    return next(Path(f) for f in files if Path(f).name.endswith(suffix))


# ---------------------------------------------------------------- editing through the API

def test_word_swap_gives_a_side_by_side_video_both_maps_and_files(client, pipe):
    video, summary, word, source_map, edited_map, files = edit(client, seed=3)
    frames = mp4_frames(video)
    assert frames.shape == (12, 272, 544, 3) and frames.std() > 5, "two 272-px preview panels, every other frame"
    assert Path(video).name.endswith("_side-by-side_preview.mp4"), "the preview first"
    assert len(files) == 8 and not any(f.endswith(".mp4") for f in files), "no video among the downloads yet"
    assert "Word swap" in summary and "“right” → “left”" in summary and "80%" in summary
    assert "Most changed" in summary and "held to the source" not in summary, "auto holds nothing in a swap"
    words = [c[0] for c in word["choices"]]
    assert words == TARGET.split() and word["value"] == words.index("left")
    left, right = plot(source_map), plot(edited_map)
    assert "source: “right”" in left["layout"]["title"]["text"]
    assert "edited: “left”" in right["layout"]["title"]["text"]
    assert left["data"][0]["zmax"] == right["data"][0]["zmax"], "both maps on one colour scale"

    expected = pipe.edit(SOURCE, TARGET, mode="swap", seed=3, seconds=1.2, steps=STEPS)
    np.testing.assert_allclose(np.load(by_name(files, "_edited_joints.npy")), expected.edited.joints, atol=1e-3)
    np.testing.assert_allclose(np.load(by_name(files, "_source_joints.npy")), expected.source.joints, atol=1e-3)
    assert np.load(by_name(files, "_edited_features.npy")).shape == (24, 263)
    assert by_name(files, "_edited.bvh").read_text().startswith("HIERARCHY")

    # The chained events: the antialiased side-by-side MP4 replaces the preview and leads the
    # downloads, then the edited motion's own video and both attention maps join them.
    full, listed, summary = client.predict("cm", api_name="/edit_video")
    assert summary == {"__type__": "update"}, "nothing refined on the way: the summary stays"
    assert Path(full).name == Path(video).name.replace("_preview.mp4", ".mp4")
    assert mp4_frames(full).shape == (24, 384, 768, 3) and [Path(f).name for f in listed][0] == Path(full).name
    assert len(listed) == 9
    everything = client.predict(api_name="/edit_files")
    names = [Path(f).name for f in everything]
    assert len(names) == 13 and names[0].endswith("_side-by-side.mp4") and names[1].endswith("_edited.mp4")
    assert mp4_frames(by_name(everything, "_edited.mp4")).shape == (24, 448, 448, 3)
    with np.load(by_name(everything, "_attention.npz")) as z:
        assert list(z["edited_words"]) == TARGET.split() and list(z["source_words"]) == SOURCE.split()
        assert z["edited_attention"].shape == (7, 7, 24) and z["source_raw"].shape[0] == STEPS
    for which in ("source", "edited"):
        assert by_name(everything, f"_attention_{which}.png").read_bytes()[:4] == b"\x89PNG"

    # Another word: the maps follow; the cached figures come back for the same word.
    src, dst = client.predict(words.index("hand"), api_name="/edit_attention")
    assert "“hand”" in plot(src)["layout"]["title"]["text"] and "“hand”" in plot(dst)["layout"]["title"]["text"]


@pytest.mark.parametrize("kwargs, expect", [
    (dict(mode="refine", target="a person waves their right hand happily and slowly"),
     ["Refinement", "“slowly”"]),
    (dict(mode="reweight", target="", word="happily", scale=-1.5), ["Re-weighted", "“happily” × -1.5"]),
    (dict(source="a person waves their left hand", mode="mirror", target="", mirror="upper"),
     ["Mirrored", "the arms"]),
    (dict(mode="swap", tau=0.5, word="left", scale=2.5, mirror="lower"),
     ["Word swap", "50%", "re-weighted", "“left” × 2.5", "mirrored", "the legs"]),
    (dict(mode="reweight", target="", word="happily", scale=2.5, hold="lower"),
     ["Re-weighted", "lower body (root path and legs) held to the source"]),
])
def test_every_edit_mode_and_their_compositions(client, kwargs, expect):
    video, summary, word, source_map, edited_map, files = edit(client, **kwargs)
    assert mp4_frames(video).shape[1:] == (272, 544, 3)
    for text in expect:
        assert text in summary, (text, summary)
    edited, source = np.load(by_name(files, "_edited_joints.npy")), np.load(by_name(files, "_source_joints.npy"))
    n = min(len(edited), len(source))
    # the tiny model reacts weakly; an edit that was not applied would leave both branches identical
    assert np.abs(edited[:n] - source[:n]).max() > 1e-5, "the edit changed the motion"
    assert plot(edited_map)["data"][0]["type"] == "heatmap"


def test_an_added_word_has_no_source_map(client):
    target = "a person waves their right hand happily and slowly"
    edit(client, mode="refine", target=target)
    src, dst = client.predict(target.split().index("slowly"), api_name="/edit_attention")
    assert "was added" in json.dumps(plot(src)) and "“slowly”" in plot(dst)["layout"]["title"]["text"]


def test_an_identical_edit_is_answered_without_sampling_again(client, server):
    first = edit(client, seed=9)
    again = edit(client, seed=9)
    assert again[0] == first[0] or Path(again[0]).read_bytes() == Path(first[0]).read_bytes()
    assert "shown again without sampling" in again[1]
    # once its full video is made, a repeat shows (and lists) it without rendering anything again
    full, *_ = client.predict("cm", api_name="/edit_video")
    on_server = next(server[1].workspace.sessions.rglob(Path(full).name))
    mtime = on_server.stat().st_mtime_ns
    third = edit(client, seed=9)
    assert Path(third[0]).name == Path(full).name and Path(third[5][0]).name == Path(full).name
    assert Path(client.predict("cm", api_name="/edit_video")[0]).name == Path(full).name
    assert on_server.stat().st_mtime_ns == mtime, "not rendered again"


@pytest.mark.parametrize("kwargs, message", [
    (dict(source=""), "source prompt is empty"),
    (dict(target=""), "word swap needs a target prompt"),
    (dict(target="x" * 400), "target prompt is 400 characters long"),
    (dict(target="a person waves their left hand very happily"), "as many words in the target prompt"),
    (dict(target=SOURCE), "same words as the source"),
    (dict(mode="twist"), "edit mode must be one of swap, refine, reweight, mirror"),
    (dict(mode="reweight", word=""), "choose the word to re-weight"),
    (dict(mode="reweight", word="jumps"), "cannot re-weight “jumps”: it is not a word of the source prompt"),
    (dict(word="right"), "not a word of the target prompt"),
    (dict(mode="reweight", word="hand", scale=5), "re-weighting scale s must be between -3 and 3"),
    (dict(tau=1.5), "tau must be between 0 and 1"),
    (dict(mirror="middle"), "mirror must be one of lower, upper, all"),
    (dict(self_inject=-0.1), "self-attention injection must be between 0 and 1"),
    (dict(hold="legs"), "hold to the source must be one of auto, lower, upper, none, got 'legs'"),
    (dict(steps=0), "steps must be between 1 and 200"),
    (dict(seconds=60.0), "seconds must be between"),
    (dict(target="a person waves their left 🖐 happily"), "cannot read “🖐” in the target prompt"),
])
def test_bad_edit_inputs_are_reported(client, kwargs, message):
    with pytest.raises(AppError, match=message):
        edit(client, **kwargs)


def test_edit_views_need_an_edit_first(client):
    for api, args in (("/edit_files", ()), ("/edit_attention", (0,)), ("/edit_video", ("cm",))):
        with pytest.raises(AppError, match="run an edit first"):
            client.predict(*args, api_name=api)


# ---------------------------------------------------------------- guided control through the API

def test_path_control_renders_targets_and_reports_its_error(client, pipe):
    video, top_view, summary, files = control(client, preset="turn-left", seconds=1.2, speed=1.2, seed=2)
    assert Path(video).name.endswith("_preview.mp4") and not any(f.endswith(".mp4") for f in files)
    full, listed, *views = client.predict("cm", api_name="/control_video")
    assert views == [{"__type__": "update"}] * 2, "nothing refined on the way: the top view and summary stay"
    assert Path(full).name == Path(video).name.replace("_preview.mp4", ".mp4")
    assert [Path(f).name for f in listed] == [Path(full).name] + [Path(f).name for f in files]
    for shown, size, n in ((video, 320, 12), (full, 448, 24)):
        frames = mp4_frames(shown)
        assert frames.shape == (n, size, size, 3)
        green = (frames[..., 1].astype(int) - frames[..., 0] > 60) & (frames[..., 1].astype(int) - frames[..., 2] > 20)
        assert green.sum(axis=(1, 2)).min() > 50, "the target path and markers are drawn in green"
    fig = plot(top_view)
    names = [t["name"] for t in fig["data"]]
    assert {"target", "achieved", "start"} <= set(names)
    assert fig["layout"]["xaxis"]["autorange"] == "reversed", "the character's left on the left"
    assert "Pelvis path: turn left" in summary and "control error: mean" in summary
    with np.load(by_name(files, "_control.npz")) as z:
        expected_signal = preset_signal("turn-left", 24, 1.2, 20)
        np.testing.assert_allclose(z["targets"], expected_signal.targets, atol=1e-6)
        assert z["mask"][:, 0, [0, 2]].all() and not z["mask"][:, 1:].any()
    expected = pipe.control("a person walks forward", signal=expected_signal, seed=2, strength=3.0, steps=STEPS)
    np.testing.assert_allclose(np.load(by_name(files, "_path_seed2_joints.npy")), expected.joints, atol=1e-3)
    mean_cm = float(summary.split("mean ")[1].split(" cm")[0])
    assert mean_cm == pytest.approx(100 * expected.info["control_mean_error_m"], abs=0.06)


def test_uploaded_targets_paths_and_mola_files_guide_the_motion(client, tmp_path, examples_dir):
    walk = synthetic_walk(28)
    targets = np.full((28, 22, 3), np.nan)
    targets[[0, -1]] = walk[[0, -1]]
    np.save(tmp_path / "keys.npy", targets)
    path = np.stack([np.linspace(0, 0.4, 24), np.linspace(0, 1.5, 24)], -1)
    path[5:9] = np.nan                       # free in between
    np.save(tmp_path / "path.npy", path)
    mola = np.zeros((20, 22, 3), np.float32)
    mola[:, 0] = np.stack([np.zeros(20), np.full(20, 0.9), np.linspace(0, 1, 20)], -1)
    np.save(tmp_path / "mola.npy", mola)

    _, _, summary, files = control(client, task="targets", upload=handle_file(str(tmp_path / "keys.npy")))
    assert "Target array" in summary and "keys\\.npy" in summary
    with np.load(by_name(files, "_control.npz")) as z:
        assert z["mask"].shape == (28, 22, 3) and z["mask"][[0, -1]].all() and not z["mask"][1:-1].any()

    _, top_view, _, files = control(client, task="targets", upload=handle_file(str(tmp_path / "path.npy")))
    with np.load(by_name(files, "_control.npz")) as z:
        assert z["mask"][:, 0, 0].sum() == 20 and not z["mask"][:, 0, 1].any()
    assert "achieved" in [t["name"] for t in plot(top_view)["data"]]

    _, _, summary, files = control(client, task="mola", upload=handle_file(str(tmp_path / "mola.npy")))
    with np.load(by_name(files, "_control.npz")) as z:
        assert z["mask"][:, 0].all() and not z["mask"][:, 1:].any()
    _, _, summary, files = control(client, task="mola", example="start_end.npy")
    assert "start\\_end\\.npy" in summary
    with np.load(by_name(files, "_control.npz")) as z:
        assert z["mask"][:4].all() and z["mask"][-4:].all() and not z["mask"][4:-4].any()


def test_inbetweening_and_upper_body_edits_start_from_the_last_generation(client):
    with pytest.raises(AppError, match="generate a motion first"):
        control(client, task="inbetween")
    out = client.predict("a person walks forward", False, 1.2, 4, STEPS, 7.5, "ddim", api_name="/generate")
    base = np.load(next(f for f in out[3] if f.endswith("seed4_joints.npy")))
    _, _, summary, files = control(client, prompt="a person runs forward", task="inbetween", keyframes="0-1, last")
    assert "In-betweening" in summary and "frames 0, 1, 23" in summary
    with np.load(by_name(files, "_control.npz")) as z:
        assert np.flatnonzero(z["mask"].any(axis=(1, 2))).tolist() == [0, 1, 23]
        np.testing.assert_allclose(z["targets"][23], base[23], atol=1e-6)
    _, _, summary, files = control(client, prompt="a person waves both hands", task="upper", strength=5)
    assert "Upper-body edit" in summary
    with np.load(by_name(files, "_control.npz")) as z:
        assert z["mask"][:, list(sk.LOWER_BODY)].all() and not z["mask"][:, list(sk.UPPER_BODY)].any()
    with pytest.raises(AppError, match="keyframe 40 is outside the last motion's frames 0..23"):
        control(client, task="inbetween", keyframes="first, 40")


def test_bad_control_inputs_are_reported_and_uploads_stay_in_the_cache(client, tmp_path):
    np.save(tmp_path / "five.npy", np.zeros((30, 5)))
    np.save(tmp_path / "short.npy", np.full((8, 2), 0.5))
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    (tmp_path / "text.npy").write_text("not an array")
    cases = [
        (dict(task="fly"), "task must be one of path, mola, targets, inbetween, upper"),
        (dict(preset="spiral"), "path must be one of straight, circle"),
        (dict(speed=9), "speed must be between 0.1 and 3"),
        (dict(seconds=0.2), "seconds must be between 0.8"),
        (dict(strength=50), "strength must be between 0 and 20"),
        (dict(prompt=""), "prompt is empty"),
        (dict(task="targets"), "upload a .npy file"),
        (dict(task="mola", example="../../etc/passwd"), "is not one of the control examples"),
        (dict(task="targets", upload=handle_file(str(tmp_path / "five.npy"))),
         r"five.npy: expected shape \(T, 22, 3\)"),
        (dict(task="targets", upload=handle_file(str(tmp_path / "short.npy"))),
         "short.npy: 8 frames; guided control needs 16"),
        (dict(task="targets", upload=handle_file(str(tmp_path / "objects.npy"))), "Python objects, which are not read"),
        (dict(task="targets", upload=handle_file(str(tmp_path / "text.npy"))), "text.npy: not a .npy array"),
    ]
    for kwargs, message in cases:
        with pytest.raises(AppError, match=message):
            control(client, **kwargs)
    # Server paths in place of an upload are refused (by Gradio's checks or the studio's own).
    for upload in (str(tmp_path / "five.npy"), {"path": "/etc/passwd", "orig_name": "passwd.npy"},
                   {"path": "/etc/passwd", "orig_name": "passwd.npy", "meta": {"_type": "gradio.FileData"}}):
        with pytest.raises(AppError):
            control(client, task="targets", upload=upload)
    assert "Pelvis path" in control(client, seconds=0.8)[2], "the server still serves"


def test_preview_shows_targets_or_says_what_is_missing(client):
    fig = plot(client.predict("path", "s-curve", 2.0, 1.0, None, "", "", api_name="/control_preview"))
    target = next(t for t in fig["data"] if t["name"] == "target")
    assert len(target["x"]) == 40
    fig = plot(client.predict("inbetween", "circle", 2.0, 1.0, None, "", "first", api_name="/control_preview"))
    assert "generate a motion first" in json.dumps(fig)


def test_edit_this_motion_fills_the_edit_tab_and_the_edit_starts_from_that_very_motion(client):
    with pytest.raises(AppError, match="generate a motion first"):
        client.predict(api_name="/edit_generated")
    prompt = "a person waves their left hand"
    out = client.predict(prompt, False, 1.6, 7, STEPS, 6.5, "ddim", False, api_name="/generate")
    shown = np.load(next(f for f in out[3] if f.endswith("seed7_joints.npy")))

    def value(update):
        return update["value"] if isinstance(update, dict) else update
    # (the tab switch is no value an API client receives)
    source, target, auto, seconds, seed, steps, cfg, sampler, foot_lock = map(
        value, client.predict(api_name="/edit_generated"))
    assert source == target == prompt
    assert (auto, seconds, seed, steps, cfg, sampler, foot_lock) == (False, 1.6, 7, STEPS, 6.5, "ddim", False)
    _, summary, _, _, _, files = client.predict(source, "mirror", "", None, "", 2.0, "all", 0.2, "auto", auto,
                                                seconds, seed, steps, cfg, sampler, foot_lock, api_name="/edit")
    assert "Sampled the edited branch (the source's sampling replayed)" in summary
    np.testing.assert_allclose(np.load(by_name(files, "_source_joints.npy")), shown, atol=1e-4)
    # another seed is another source: both branches are sampled
    _, summary, *_ = client.predict(source, "mirror", "", None, "", 2.0, "all", 0.2, "auto", auto, seconds, 8,
                                    steps, cfg, sampler, foot_lock, api_name="/edit")
    assert "Sampled both branches" in summary


def test_every_new_event_has_an_api_name(server):
    names = {fn.api_name for fn in server[1].demo.fns.values()}
    assert {"edit", "edit_generated", "edit_video", "edit_files", "edit_attention", "control", "control_video",
            "control_preview"} <= names


# ---------------------------------------------------------------- the pieces

@pytest.mark.parametrize("preset", list(PRESETS))
def test_preset_paths_start_forward_and_have_the_asked_length(preset):
    p = preset_polyline(preset, 3.0)
    assert np.allclose(p[0], 0) and np.linalg.norm(np.diff(p, axis=0), axis=1).sum() == pytest.approx(3.0)
    heading = p[1] - p[0]
    assert heading[1] > abs(heading[0]), "leaves the origin heading forward (+z)"
    end = p[-1]
    if preset == "circle":
        assert np.allclose(end, 0, atol=1e-9) and p[:, 0].max() > 0.9, "closes, to the left (+x)"
    if preset == "turn-left":
        assert end[0] > 0.5 and np.allclose(p[-2:, 1], p[-1, 1])
    if preset == "turn-right":
        assert end[0] < -0.5
    sig = preset_signal(preset, 40, 1.0, 20)
    path = pelvis_path(sig)
    assert path.shape == (40, 3) and (path[:, 1] == 0).all()
    assert np.linalg.norm(np.diff(path[:, [0, 2]], axis=0), axis=1).sum() == pytest.approx(39 / 20, rel=0.02)


def test_keyframes_are_parsed_and_checked():
    assert parse_keyframes("first, last", 40) == (0, 39)
    assert parse_keyframes("0-3; 36-39 20", 40) == (0, 1, 2, 3, 20, 36, 37, 38, 39)
    assert parse_keyframes([5, "last"], 10) == (5, 9)
    for spec, message in (("", "give the keyframes"), ("soon", "not a frame number"), ("5-2", "runs backwards"),
                          ("-1", "not a frame number"), ("0-99", "outside"), (3.5, "must be text")):
        with pytest.raises(ValueError, match=message):
            parse_keyframes(spec, 40)
    first_and_last = np.where(np.arange(40)[:, None, None] % 39 == 0, synthetic_walk(40), np.nan)
    assert pelvis_path(make_signal(first_and_last)) is None, "two keyframes are no path"


def test_uploads_are_checked_before_they_are_read(tmp_path):
    root = tmp_path / "cache"
    root.mkdir()
    big = root / "big.npy"
    np.save(big, np.zeros(MAX_UPLOAD_BYTES // 8 + 10))
    with pytest.raises(ValueError, match="big.npy: 4.0 MB is more than the 4 MB"):
        upload_file({"path": str(big), "orig_name": "big.npy"}, root)
    np.save(root / "ok.npy", np.zeros((20, 2)))
    (root / "ok.txt").write_text("x")
    up = upload_file({"path": str(root / "ok.npy"), "orig_name": "<b>my<b> path.npy"}, root)
    assert up.name == "_b_my_b_ path.npy" and len(up.digest) == 64
    with pytest.raises(ValueError, match="expected a NumPy .npy file"):
        upload_file(str(root / "ok.txt"), root)
    with pytest.raises(ValueError, match="not found on the server"):
        upload_file(str(root / ".." / "cache" / ".." / "outside.npy"), root)
    assert upload_file(None, root) is None and display_name("") == "the uploaded file"
    assert display_name("C:\\Users\\me\\a b.npy") == "a b.npy"


def test_edit_and_control_validation_directly(pipe, tmp_path):
    req = parse_edit(pipe, "  a person walks ", "refine", "a person walks slowly", None, "SLOWLY", "1.5", "none",
                     0.1, "upper", True, None, 1, 3, 5, "dpm")
    assert req == EditRequest("a person walks", "a person walks slowly", "refine", 0.0, (("slowly", 1.5),), None, 0.1,
                              "upper", None, 1, 3, 5.0, "dpm")
    assert req.spec.hold == "upper"
    swap = parse_edit(pipe, SOURCE, "swap", TARGET, None, "", 1, "none", 0.2, "auto", True, None, 0, 3, 5, "ddim")
    assert (swap.tau, swap.hold) == (0.8, "auto")
    mirror = parse_edit(pipe, SOURCE, "mirror", "ignored", 0.3, "", 1, "all", 0.2, "none", False, 1.2, 0, 3, 5, "ddim")
    assert (mirror.target, mirror.tau, mirror.mirror, mirror.hold, mirror.seconds) == (None, None, "all", None, 1.2)
    assert parse_edit(pipe, SOURCE, "mirror", "", None, "", 1, "none", 0.2, "auto", True, None, 0, 3, 5,
                      "ddim").mirror == "all"
    walk = synthetic_walk(24)
    base = Result(None, type("M", (), {"joints": walk})(), tmp_path)
    req, sig = parse_control(pipe, "a person walks", "upper", None, None, None, None, None, None, 2, 0, 3, 5, base=base)
    assert req == ControlRequest("a person walks", "upper", (), base.id, 2.0, 0, 3, 5.0)
    np.testing.assert_array_equal(sig.mask, lower_body_signal(walk).mask)


def test_motion_difference_locates_the_change():
    a = synthetic_walk(30)
    b = a.copy()
    right_arm = np.flatnonzero(sk.PART_OF_JOINT == sk.BODY_PARTS.names.index("right_upper"))
    b[:, right_arm, 1] += 0.3
    d = motion_difference(a, b[:20])
    assert d.most_changed[0] == "right upper" and d.most_changed[1] == pytest.approx(0.3)
    assert d.root_change_m == 0 and d.frames == (30, 20) and "root" not in d.part_change_m


def test_top_view_draws_keyframes_apart():
    t = np.full((20, 22, 3), np.nan)
    t[[0, 1, 10, 19], 0] = [[0, 0.9, 0], [0.1, 0.9, 0.1], [0.5, 0.9, 1], [0, 0.9, 2]]
    sig = make_signal(t)
    fig = control_top_view(sig.targets, sig.mask, synthetic_walk(20))
    target = next(tr for tr in fig.data if tr.name == "target")
    assert [x is None for x in target.x] == [False, False, True, False, True, False], "separate keyframes stay apart"
    assert [x for x in target.x if x is not None] == pytest.approx([0, 0.1, 0.5, 0])


def test_sessions_reuse_identical_requests_per_kind(pipe, tmp_path):
    ws = Workspace(tmp_path)
    studio = Studio(pipe, ws)
    try:
        session = studio.session(None, "client")
        req = parse_edit(pipe, SOURCE, "mirror", "", None, "", 1, "upper", 0.2, "auto", False, 0.8, 0, 2, 5, "ddim")
        first = studio.edit(session, req, lambda *a: None)
        other = studio.edit(session, parse_edit(pipe, SOURCE, "mirror", "", None, "", 1, "lower", 0.2, "auto", False,
                                                0.8, 0, 2, 5, "ddim"), lambda *a: None)
        assert studio.edit(session, req) is first and session.latest("edit") is first and first.reused == 1
        assert session.current is None, "edits are not generations"
        first.files["preview"].unlink()               # a pruned file: sampled again
        again = studio.edit(session, req)
        assert again is not first and session.latest("edit") is again
        assert first.folder.exists() and not other.folder.exists(), "the oldest of the kept results goes"
        assert isinstance(Session("k", tmp_path / "s").latest("control"), type(None))
    finally:
        studio.close()
        ws.close()


def test_edits_and_guided_motions_preview_first_and_render_in_full_once(pipe, tmp_path, monkeypatch):
    import salad.render as render

    calls = []
    for name in ("render_video", "render_side_by_side"):
        def recorded(first, path_or_labels, *args, real=getattr(render, name), name=name, **kwargs):
            path = path_or_labels if name == "render_video" else args[0]
            calls.append((name, Path(path).name, kwargs.get("antialias", True)))
            return real(first, path_or_labels, *args, **kwargs)
        monkeypatch.setattr(render, name, recorded)
    ws = Workspace(tmp_path)
    studio = Studio(pipe, ws)
    try:
        session = studio.session(None, "client")
        req = parse_edit(pipe, SOURCE, "mirror", "", None, "", 1, "upper", 0.2, "auto", False, 0.8, 0, 2, 5, "ddim")
        edited = studio.edit(session, req)
        assert calls == [("render_side_by_side", edited.files["preview"].name, False)]
        assert edited.files["preview"].name.endswith("_side-by-side_preview.mp4")
        assert len(studio.downloads(edited)) == 8 and studio.shown_video(edited) == edited.files["preview"]
        full = studio.full_video(edited)
        assert calls[-1] == ("render_side_by_side", full.name, True) and full.name.endswith("_side-by-side.mp4")
        everything = studio.edit_downloads(edited)
        assert len(everything) == 13 and everything[0] == full and edited.files["preview"] not in everything
        assert calls[-1][0] == "render_video" and calls[-1][1].endswith("_edited.mp4") and len(calls) == 3
        assert studio.edit(session, req) is edited and studio.edit_downloads(edited) == everything
        assert studio.shown_video(edited) == full and len(calls) == 3, "nothing rendered again"

        calls.clear()
        creq, signal = parse_control(pipe, "a person walks forward", "path", "circle", 1.2, 1.0, None, "", "", 2.0,
                                     0, 2, 5.0, True, "ddim")
        guided = studio.control(session, creq, signal)
        assert calls == [("render_video", guided.files["preview"].name, False)]
        assert [p.name for p in studio.downloads(guided)][-1].endswith("_control.npz")
        full = studio.full_video(guided)
        assert calls[-1] == ("render_video", full.name, True) and studio.downloads(guided)[0] == full
        assert studio.control(session, creq, signal) is guided and studio.full_video(guided) == full
        assert len(calls) == 2
    finally:
        studio.close()
        ws.close()


def test_examples_folder_setting_is_checked(tmp_path):
    from app.cli import parse_args

    assert parse_args(["--control-examples", str(tmp_path)]).control_examples == tmp_path
    with pytest.raises(ValueError, match="control examples folder does not exist"):
        Settings(control_examples=tmp_path / "missing")
