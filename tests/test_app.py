"""The studio end to end through its API (gradio_client), on the tiny trained model: generation,
attention views, validation, concurrent sessions, served files, the no-model page, and the
studio's own pieces (validation, caching, clean-up) directly."""
import base64
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import app  # noqa: F401  (switches analytics and hub look-ups off before gradio is imported)
import httpx
import numpy as np
import pytest
from gradio_client import Client
from gradio_client.exceptions import AppError

from salad.editing.store import AttentionMaps
from salad.files import atomic_write
from salad.motion.control import control_errors
from salad.motion.bvh import load_bvh

from app.figures import frames_to_restyle_slider, plot_data
from app.session import KEEP_RESULTS, Result, ResultGone, Session
from app.settings import Settings
from app.studio import Studio, file_stem, word_tint
from app.ui.handlers import word_choices
from app.validation import EditRequest, GenerateRequest, parse_attention, parse_control, parse_generate
from app.workspace import Workspace
from conftest import free_port, mp4_frames, serve_studio, synthetic_walk

REPO = Path(__file__).resolve().parents[1]
STEPS = 6


@pytest.fixture(scope="module")
def server(pipe, tmp_path_factory):
    with serve_studio(pipe, tmp_path_factory.mktemp("studio")) as served:
        yield served


def generate(client, prompt, seconds=1.6, seed=0, steps=STEPS, cfg=7.5, sampler="ddim", foot_lock=None):
    """foot_lock=None leaves it out, as a client written before the switch existed does (it defaults to on)."""
    extra = () if foot_lock is None else (foot_lock,)
    return client.predict(prompt, seconds is None, seconds, seed, steps, cfg, sampler, *extra, api_name="/generate")


def plotly_array(value) -> np.ndarray:
    """A data array of a Plotly figure's JSON: a list, or base64 binary ({"dtype", "bdata", "shape"})."""
    if isinstance(value, dict) and "bdata" in value:
        arr = np.frombuffer(base64.b64decode(value["bdata"]), dtype=value["dtype"])
        return arr.reshape([int(n) for n in str(value.get("shape", len(arr))).split(",")])
    return np.asarray(value, dtype=float)


# ---------------------------------------------------------------- the API

def test_the_studio_draws_its_videos_with_a_render_worker(client):
    """The server starts one render worker beside it (--render-workers, default 1), which draws a share of
    each preview's frames; what it draws is checked against this process's own in test_render_workers."""
    from app.cli import parse_args
    from salad.render import workers

    assert Settings().render_workers == 1 and parse_args([]).render_workers == 1
    assert parse_args(["--render-workers", "0"]).render_workers == 0
    with pytest.raises(ValueError, match="render workers must be in 0..7"):
        Settings(render_workers=8)
    workers.wait_ready(1)
    worker = workers.running()[0]
    before = worker.jobs
    video = generate(client, "a person walks forward", seconds=1.6, seed=7)[0]
    assert mp4_frames(video).shape[:3] == (16, 320, 320) and 16 >= workers.MIN_SHARED_FRAMES
    assert worker.jobs > before, "the worker drew a share of the preview"


def test_generate_returns_video_figure_and_files(client, pipe):
    out = generate(client, "a person waves their right hand happily", seconds=1.6, seed=3)
    video, skeleton, summary, files, words, layers, first, last, heatmap, word_video = out
    frames = mp4_frames(video)
    assert frames.shape == (16, 320, 320, 3) and frames.std() > 5, "a decodable, non-blank preview of every other frame"
    stem = "a-person-waves-their-right-hand-happily_seed3"
    assert Path(video).name == f"{stem}_preview.mp4", "the preview first; the antialiased MP4 follows"
    assert skeleton["type"] == "plotly"
    fig = json.loads(skeleton["plot"])
    steps = fig["layout"]["sliders"][0]["steps"]
    assert len(steps) == 32 and steps[5]["method"] == "update" and not fig.get("frames")
    assert "happily" in summary and "32 frames" in summary and "seed 3" in summary
    names = [Path(f).name for f in files]
    assert names == [f"{stem}.bvh", f"{stem}_joints.npy", f"{stem}_features.npy", f"{stem}.npz"], \
        "the MP4 joins the downloads once rendered; the preview never does"
    by_ext = {Path(f).suffix: Path(f) for f in files if not f.endswith("_features.npy")}
    joints = np.load(by_ext[".npy"])
    np.testing.assert_array_equal(np.load(files[2]).shape, (32, 263))
    assert joints.shape == (32, 22, 3) and joints.dtype == np.float32 and np.isfinite(joints).all()
    with np.load(by_ext[".npz"]) as z:
        np.testing.assert_array_equal(z["joints"], joints)
        assert z["features"].shape == (32, 263)
    assert by_ext[".bvh"].read_text().startswith("HIERARCHY")
    assert load_bvh(by_ext[".bvh"]).scale == 0.01                      # downloads are in centimetres
    expected = pipe.generate("a person waves their right hand happily", seconds=1.6, seed=3, steps=STEPS,
                             return_attention=True)
    np.testing.assert_allclose(joints, expected.joints, atol=1e-3)
    assert [c[0] for c in words["choices"]] == ["a", "person", "waves", "their", "right", "hand", "happily"]
    assert layers["value"] == [0, 1, 2] and (first["value"], last["value"]) == (1, STEPS)
    assert heatmap is None and word_video is None

    # the chained event: the antialiased MP4 takes the preview's place and leads the downloads
    full, listed, skeleton, summary = client.predict("cm", api_name="/generate_video")
    # nothing was refined on the way (this pipeline does not refine): the 3D view and summary stay as drawn
    assert skeleton == summary == {"__type__": "update"}
    assert Path(full).name == f"{stem}.mp4" and [Path(f).name for f in listed] == [f"{stem}.mp4"] + names
    full_frames = mp4_frames(full)
    assert full_frames.shape == (32, 448, 448, 3), "the full video, at full size"


def test_an_identical_request_shows_its_full_video_without_rendering_again(server, client):
    _, studio_app = server
    first = generate(client, "a person bows", seconds=1.2, seed=21)
    assert Path(first[0]).name.endswith("_preview.mp4")
    full, *_ = client.predict("cm", api_name="/generate_video")
    on_server = next(studio_app.workspace.sessions.rglob(Path(full).name))
    mtime = on_server.stat().st_mtime_ns
    again = generate(client, "a person bows", seconds=1.2, seed=21)
    assert Path(again[0]).name == Path(full).name, "answered with the full video rendered before"
    assert Path(again[3][0]).name == Path(full).name and "shown again without sampling" in again[2]
    full_again, listed, *_ = client.predict("cm", api_name="/generate_video")
    assert Path(full_again).name == Path(full).name and len(listed) == 5
    assert on_server.stat().st_mtime_ns == mtime, "not rendered again"
    assert len(list(on_server.parent.glob("*.mp4"))) == 2, "one preview, one full video"


def test_the_full_video_needs_a_result_first(client):
    with pytest.raises(AppError, match="generate a motion first"):
        client.predict("cm", api_name="/generate_video")


def test_bvh_downloads_come_in_the_chosen_units(client):
    """Centimetres as saved; metres written beside them on demand and listed in their place."""
    before = client.predict("m", api_name="/bvh_units")
    assert before is None or before == [] or isinstance(before, (list, dict)), "no motion yet: nothing to list"
    out = generate(client, "a person walks forward", seconds=1.6, seed=5)
    cm = next(Path(f) for f in out[3] if f.endswith(".bvh"))
    files = client.predict("m", api_name="/bvh_units")
    names = [Path(f).name for f in files]
    assert names[0] == cm.stem + "_m.bvh" and len(names) == 4 and names[1].endswith("_joints.npy")
    in_m, in_cm = load_bvh(files[0]), load_bvh(cm)
    np.testing.assert_allclose(in_m.joints, in_cm.joints, atol=1e-4)
    offsets = lambda path: [float(x) for line in Path(path).read_text().splitlines()  # noqa: E731
                            if line.strip().startswith("OFFSET") for x in line.split()[1:]]
    np.testing.assert_allclose(np.array(offsets(cm)), 100 * np.array(offsets(files[0])), atol=1e-3)
    assert Path(client.predict("cm", api_name="/bvh_units")[0]).name == cm.name
    # the full video's event relists the downloads in the chosen units, its MP4 first
    _, listed, *_ = client.predict("m", api_name="/generate_video")
    assert [Path(f).name for f in listed][:2] == [cm.stem + ".mp4", cm.stem + "_m.bvh"] and len(listed) == 5
    with pytest.raises(AppError, match="BVH units must be one of cm, m"):
        client.predict("inch", api_name="/bvh_units")


def test_foot_lock_switch_reaches_the_pipeline_and_the_summary(client, pipe):
    prompt, seconds, seed, steps = "a person walks forward", 1.2, 4, 5
    on = generate(client, prompt, seconds=seconds, seed=seed, steps=steps, foot_lock=True)
    off = generate(client, prompt, seconds=seconds, seed=seed, steps=steps, foot_lock=False)
    joints = {}
    for name, out in (("on", on), ("off", off)):
        joints[name] = np.load(next(f for f in out[3] if f.endswith("_joints.npy")))
    assert "Foot lock" in on[2] and "Foot lock" not in off[2]
    assert Path(on[3][0]).parent != Path(off[3][0]).parent, "the switch is part of the request: no reuse"
    locked = pipe.generate(prompt, seconds=seconds, seed=seed, steps=steps, return_attention=True)
    raw = pipe.generate(prompt, seconds=seconds, seed=seed, steps=steps, return_attention=True, foot_lock=False)
    np.testing.assert_allclose(joints["on"], locked.joints, atol=1e-3)
    np.testing.assert_allclose(joints["off"], raw.joints, atol=1e-3)
    pinned = sum(locked.info["foot_lock"]["footsteps"].values())
    if pinned:
        assert f"{pinned} footstep" in on[2] and not np.allclose(joints["on"], joints["off"], atol=1e-4)
    else:
        assert "no planted footsteps" in on[2]


def test_attention_views_follow_word_layers_and_steps(client):
    generate(client, "a person raises their left hand", seconds=1.2, seed=1)
    heatmap, overview, files = client.predict("left", [0, 1, 2], 1, STEPS, api_name="/attention")
    h = json.loads(heatmap["plot"])
    assert h["data"][0]["type"] == "heatmap" and "left" in h["layout"]["title"]["text"]
    z = plotly_array(h["data"][0]["z"])
    assert z.shape == (7, 24) and (z >= 0).all()
    o = json.loads(overview["plot"])
    assert len([t for t in o["data"] if t["type"] == "heatmap"]) == 6
    npz, png = sorted(files, key=lambda f: Path(f).suffix)
    assert Path(png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with np.load(npz) as a:
        assert a["attention"].shape == (6, 7, 24) and list(a["words"])[4] == "left"
        np.testing.assert_allclose(a["attention"][4], z, atol=1e-6)
        assert a["raw"].shape[:2] == (STEPS, 3)

    # Another aggregation gives other numbers; a word given by index is the same word.
    h2, _, files2 = client.predict(4, [1], 2, 4, api_name="/attention")
    z2 = plotly_array(json.loads(h2["plot"])["data"][0]["z"])
    assert z2.shape == z.shape and not np.allclose(z2, z)
    assert {Path(f).name for f in files2}.isdisjoint({Path(f).name for f in files})

    tinted = mp4_frames(client.predict("left", [0, 1, 2], 1, STEPS, api_name="/attention_video"))
    assert tinted.shape == (24, 448, 448, 3)
    assert client.predict(None, [0, 1, 2], 1, STEPS, api_name="/attention_video") is None


@pytest.mark.parametrize("args, message", [
    (("", True, 1.0, 0, STEPS, 7.5, "ddim"), "prompt is empty"),
    (("x" * 400, True, 1.0, 0, STEPS, 7.5, "ddim"), "limit is 300"),
    (("a person walks", False, 100.0, 0, STEPS, 7.5, "ddim"), "seconds must be between 0.8 and 2"),
    (("a person walks", False, "soon", 0, STEPS, 7.5, "ddim"), "seconds must be a number"),
    (("a person 🕺 dances", True, 1.0, 0, STEPS, 7.5, "ddim"), "cannot read “🕺”"),
    (("a person walks", True, 1.0, -1, STEPS, 7.5, "ddim"), "seed must be between 0 and 2147483647"),
    (("a person walks", True, 1.0, 1.5, STEPS, 7.5, "ddim"), "seed must be a whole number"),
    (("a person walks", True, 1.0, 0, 100000, 7.5, "ddim"), "steps must be between 1 and 200"),
    (("a person walks", True, 1.0, 0, STEPS, 1e9, "ddim"), "CFG scale must be between 0 and 15"),
    (("a person walks", True, 1.0, 0, STEPS, 7.5, "euler"), "sampler must be one of ddim, dpm"),
    ((["a person walks"], True, 1.0, 0, STEPS, 7.5, "ddim"), "prompt must be a string"),
    (("a person walks", "yes", 1.0, 0, STEPS, 7.5, "ddim"), "automatic length must be true or false"),
    (("a person walks", True, 1.0, 0, STEPS, 7.5, "ddim", "yes"), "foot lock must be true or false"),
])
def test_bad_generate_inputs_are_reported(client, args, message):
    with pytest.raises(AppError, match=message):
        client.predict(*args, api_name="/generate")


def test_bad_attention_requests_are_reported_and_the_server_keeps_serving(client):
    with pytest.raises(AppError, match="generate a motion first"):
        client.predict("walks", [0], 1, STEPS, api_name="/attention")
    generate(client, "someone walks and turns left", seconds=1.0, seed=2)
    for args, message in ((("jumps", [0], 1, STEPS), "not a word of the prompt"),
                          ((99, [0], 1, STEPS), "word must be between 0 and 4"),
                          (("walks", [], 1, STEPS), "at least one layer"),
                          (("walks", [7], 1, STEPS), "layer must be between 0 and 2"),
                          (("walks", "0", 1, STEPS), "layers must be a list"),
                          (("walks", [0], 4, 2), "comes after the last step"),
                          (("walks", [0], 1, STEPS + 1), f"last step must be between 1 and {STEPS}")):
        with pytest.raises(AppError, match=message):
            client.predict(*args, api_name="/attention")
    heatmap, _, _ = client.predict("walks", [0], 1, STEPS, api_name="/attention")
    assert heatmap["type"] == "plotly"


def test_eight_simultaneous_sessions_get_their_own_motions(server, pipe, tmp_path):
    url, studio_app = server
    jobs = [(f"a person {verb}", seconds, seed) for verb, seconds, seed in (
        ("walks forward", 0.8, 11), ("runs forward", 1.0, 12), ("waves their left hand", 1.2, 13),
        ("waves their right hand", 1.4, 14), ("bows", 1.6, 15), ("kicks", 1.8, 16), ("dances", 2.0, 17),
        ("raises both hands", None, 18))]
    expected = [pipe.generate(p, seconds=s, seed=seed, steps=STEPS, return_attention=True).joints
                for p, s, seed in jobs]

    def run(i):
        c = Client(url, verbose=False, download_files=str(tmp_path / str(i)), analytics_enabled=False)
        prompt, seconds, seed = jobs[i]
        out = generate(c, prompt, seconds=seconds, seed=seed)
        npy = next(f for f in out[3] if f.endswith("_joints.npy"))
        # the client is kept: a session whose client has gone is closed and its folder removed
        return np.load(npy), out[2], [w[0] for w in out[4]["choices"]], c

    started = time.perf_counter()
    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(run, range(8)))
    elapsed = time.perf_counter() - started
    for i, (joints, summary, words, _) in enumerate(results):
        prompt, seconds, seed = jobs[i]
        assert joints.shape == expected[i].shape, f"session {i} got another session's length"
        np.testing.assert_allclose(joints, expected[i], atol=1e-3, err_msg=f"session {i}")
        others = [np.abs(joints - e).max() for j, e in enumerate(expected) if j != i and e.shape == joints.shape]
        assert all(d > 1e-2 for d in others), f"session {i} matches another session's motion"
        assert f"seed {seed}" in summary and prompt in summary and words == prompt.split()
    sessions = list(studio_app.workspace.sessions.iterdir())
    assert len(sessions) >= 8, "one folder per session"
    print(f"8 sessions served in {elapsed:.1f} s")


def test_a_sessions_files_their_served_copies_and_its_uploads_go_when_it_ends(server, tmp_path, monkeypatch):
    """A tab that closes ends its session (its heartbeat stops): the session's folder, the copies
    Gradio serves of its files and the files it uploaded are removed at once, and their URLs fail."""
    from gradio.processing_utils import hash_file
    from gradio_client import handle_file

    monkeypatch.setenv("GRADIO_HEARTBEAT_INTERVAL", "0.5")   # notice the closed connection quickly
    url, studio_app = server
    ws = studio_app.workspace
    session = "a-session-that-ends"
    np.save(tmp_path / "my-own-walk.npy", synthetic_walk(40))
    c = Client(url, verbose=False, download_files=str(tmp_path / "dl"), analytics_enabled=False)
    c.session_hash = session
    try:
        with httpx.stream("GET", f"{url}gradio_api/heartbeat/{session}", timeout=60) as beat:
            lines = beat.iter_lines()     # kept: dropping the iterator closes the connection
            next(lines)                   # the session is open, as a tab's
            generate(c, "a person walks forward", seconds=1.6, seed=11)
            assert c.predict(handle_file(str(tmp_path / "my-own-walk.npy")), api_name="/real_upload") == ""
            folder = ws.sessions / ws.session_key(session)
            served = [ws.gradio_cache / hash_file(f) / f.name for f in folder.rglob("*") if f.is_file()]
            uploads = list(ws.gradio_cache.rglob("my-own-walk.npy"))
            assert len(served) == 5 and all(p.is_file() for p in served) and len(uploads) == 1
            links = [f"{url}gradio_api/file={p}" for p in served]
            assert all(httpx.get(link).status_code == 200 for link in links)
            c.close()          # the client keeps a heartbeat of its own for the session it uses
        deadline = time.time() + 30
        while (folder.exists() or any(p.exists() for p in served + uploads)) and time.time() < deadline:
            time.sleep(0.2)
        assert not folder.exists() and not any(p.exists() for p in served + uploads)
        # Gradio refuses a path it no longer holds (403), as it refuses any path it never served
        assert {httpx.get(link).status_code for link in links} <= {403, 404}
    finally:
        c.close()


def test_only_the_studios_outputs_are_served(server, client):
    url, studio_app = server
    generate(client, "a person bows", seconds=0.8, seed=5)
    with httpx.Client(base_url=url, timeout=30) as http:
        for path in ("/etc/passwd", str(REPO / "pyproject.toml"), str(studio_app.workspace.root / "owner.pid"),
                     str(next(studio_app.workspace.sessions.rglob("*.npy")))):
            r = http.get(f"/gradio_api/file={path}")
            assert r.status_code == 403, path
        assert http.get("/").status_code == 200
    assert studio_app.demo.share is False and studio_app.demo.server_name == "127.0.0.1"


def test_every_event_has_an_api_name(server):
    _, studio_app = server
    names = [fn.api_name for fn in studio_app.demo.fns.values()]
    assert all(names) and {"generate", "generate_video", "attention", "attention_video"} <= set(names)


def test_videos_render_apart_from_the_views(server):
    """A word click (its heatmap) and a downloads relisting queue as "views"; every video renders in
    "render": neither waits for the other."""
    groups = {fn.api_name: fn.concurrency_id for fn in server[1].demo.fns.values()}
    for name in ("generate_video", "edit_video", "control_video", "attention_video", "edit_files"):
        assert groups[name] == "render", name
    for name in ("attention", "attention_refresh", "bvh_units", "edit_attention"):
        assert groups[name] == "views", name
    assert groups["generate"] == groups["edit"] == groups["control"] == "model"


def test_without_a_model_the_studio_shows_why(tmp_path):
    port = free_port()
    env = dict(os.environ, OMP_NUM_THREADS="1", TMPDIR=str(tmp_path))
    env.pop("SALAD_MODEL", None)
    proc = subprocess.Popen([sys.executable, "-m", "app", "--model", str(tmp_path / "nowhere"), "--port", str(port)],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            try:
                if httpx.get(url + "/config", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.5)
        assert proc.poll() is None, proc.stdout.read()[-3000:]
        config = httpx.get(url + "/config", timeout=10).text
        assert "could not load a model" in config and "nowhere" in config and "--model" in config
        assert len(list(tmp_path.glob("salad-studio-*"))) == 1
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert proc.returncode == 0
    assert not list(tmp_path.glob("salad-studio-*")), "the temp root is removed on exit"


# ---------------------------------------------------------------- the pieces

def test_generate_validation_uses_the_pipelines_limits(pipe):
    req = parse_generate(pipe, "  a person   walks ", False, 1.2, 7.0, 20.0, 3, "dpm")
    assert req == GenerateRequest("a person walks", 1.2, 7, 20, 3.0, "dpm")
    assert parse_generate(pipe, "a person walks", True, "ignored", 0, 1, 0, "ddim").seconds is None
    assert req.foot_lock is True
    assert parse_generate(pipe, "a person walks", True, None, 0, 1, 0, "ddim", 0).foot_lock is False
    with pytest.raises(ValueError, match="seconds is required"):
        parse_generate(pipe, "a person walks", False, None, 0, 1, 0, "ddim")
    with pytest.raises(ValueError, match="steps must be a number"):
        parse_generate(pipe, "a person walks", True, None, 0, True, 0, "ddim")
    with pytest.raises(ValueError, match="CFG scale must be a finite number"):
        parse_generate(pipe, "a person walks", True, None, 0, 10, float("nan"), "ddim")


def test_attention_validation():
    maps = AttentionMaps(words=["a", "person", "waves", "a", "hand"], data=np.zeros((10, 2, 5, 7, 4), np.float32),
                         frames=16, layers=[1, 3])
    r = parse_attention(maps, "Hand", [3, 1, 3], 2, 10)
    assert (r.word, r.layers, r.steps) == (4, (1, 3), (1, 10))
    assert parse_attention(maps, "", [1], 1, 1).word is None
    assert parse_attention(maps, "3", [1], 1, 1).word == 3
    with pytest.raises(ValueError, match="were not captured"):
        parse_attention(maps, 0, [2], 1, 1)
    assert word_choices(maps.words) == [("a (1)", 0), ("person", 1), ("waves", 2), ("a (2)", 3), ("hand", 4)]


def test_word_tint_scales_a_words_map_onto_joints():
    att = np.zeros((7, 5))
    att[5] = [0.0, 0.1, 0.2, 0.4, 0.2]          # right upper body only
    tint = word_tint(att)
    assert tint.shape == (5, 22) and tint.max() == 1.0
    from salad.motion.skeleton import PART_OF_JOINT
    assert (tint[:, PART_OF_JOINT != 5] == 0).all() and (tint[3, PART_OF_JOINT == 5] == 1).all()
    assert not word_tint(np.zeros((7, 3))).any()


def test_restyle_slider_keeps_every_frame():
    import gradio as gr

    from salad.render import skeleton_figure_spec

    joints = synthetic_walk(30)
    spec = skeleton_figure_spec(joints)
    fig = frames_to_restyle_slider(spec)
    steps = fig["layout"]["sliders"][0]["steps"]
    assert len(steps) == 30 and not fig.get("frames") and not fig["layout"].get("updatemenus")
    z_up = np.asarray(steps[17]["args"][0]["z"][0], dtype=float)
    assert np.nanmax(z_up) == pytest.approx(joints[17, :, 1].max(), abs=1e-6)  # plot z is the data's y
    # the box follows the body: the step also moves the scene's ranges, by dotted keys (the camera stays)
    assert steps[17]["method"] == "update" and list(steps[17]["args"][2]) == [2]
    x0, x1 = steps[17]["args"][1]["scene.xaxis.range"]
    assert (x0 + x1) / 2 == pytest.approx(joints[17, 0, 2], abs=1e-6)
    assert set(steps[17]["args"][1]) == {"scene.xaxis.range", "scene.yaxis.range"}
    # without the play button the slider takes the full width
    assert (fig["layout"]["sliders"][0]["x"], fig["layout"]["sliders"][0]["len"]) == (0, 1)
    # the input spec is left as it was
    assert len(spec["frames"]) == 30 and spec["layout"]["updatemenus"]
    assert spec["layout"]["sliders"][0]["steps"][17]["method"] == "animate"
    # what gr.Plot is given: plotly JSON (no NaN, which is not JSON) that Gradio passes on unchanged
    data = plot_data(fig)
    assert data.type == "plotly" and gr.Plot().postprocess(data) is data
    sent = json.loads(data.plot)
    assert not sent.get("frames") and len(sent["layout"]["sliders"][0]["steps"]) == 30
    assert sent["data"][2]["x"][2] is None                                 # a break in the bone polyline


def test_file_stems_are_safe():
    req = GenerateRequest("../../etc/passwd; rm -rf / “quoted”", None, 4, 10, 7.5, "ddim")
    stem = file_stem(req)
    assert stem.endswith("_seed4") and "/" not in stem and "." not in stem and " " not in stem


def test_workspace_sessions_are_private_pruned_and_removed(tmp_path):
    ws = Workspace(tmp_path, ttl_s=60)
    try:
        a, b = ws.session_dir("abc"), ws.session_dir("../../x")
        assert a.parent == b.parent == ws.sessions and a != b
        old = time.time() - 120
        os.utime(a, (old, old))
        assert ws.prune() == 1 and not a.exists() and b.exists()
        ws.remove_session("../../x")
        assert not b.exists()
        # A root whose process is gone is removed by the next workspace; a live one is kept.
        dead = tmp_path / "salad-studio-dead"
        dead.mkdir()
        (dead / "owner.pid").write_text("999999999")
        Workspace(tmp_path).close()
        assert not dead.exists() and ws.root.exists()
    finally:
        ws.close()
    assert not ws.root.exists()


def test_studio_close_stops_its_model_thread(pipe, tmp_path):
    ws = Workspace(tmp_path)
    try:
        studio = Studio(pipe, ws)
        assert studio.model_thread.run(threading.current_thread) is not threading.current_thread()
        studio.close()
        with pytest.raises(RuntimeError):
            studio.model_thread.run(lambda: None)
    finally:
        ws.close()


def test_sessions_keep_recent_results_and_cache_renders(pipe, tmp_path):
    ws = Workspace(tmp_path)
    studio = Studio(pipe, ws)
    try:
        session = studio.session(None, "client-1")
        reqs = [GenerateRequest("a person waves their left hand", 1.0, seed, 3, 7.5, "ddim")
                for seed in range(KEEP_RESULTS + 1)]
        stages = []
        results = [studio.generate(session, req, lambda s, i, n: stages.append(s)) for req in reqs]
        assert {"sampling", "rendering"} <= set(stages)
        assert not results[0].folder.exists() and all(r.folder.exists() for r in results[1:])
        # the same request again is answered from the kept result, which becomes current
        stages.clear()
        assert studio.generate(session, reqs[1], lambda s, i, n: stages.append(s)) is results[1] and not stages
        assert session.current is results[1] and results[1].reused == 1
        current = studio.generate(session, reqs[-1])
        assert current is results[-1] and session.current is current
        areq = parse_attention(current.motion.attention, "left", [0, 1, 2], 1, 3)
        first = studio.word_video(current, areq)
        mtime = first.stat().st_mtime_ns
        assert studio.word_video(current, areq) == first and first.stat().st_mtime_ns == mtime, "cached"
        assert studio.word_heatmap(current, areq) is studio.word_heatmap(current, areq)
        first.unlink()                       # pruned files are made again
        assert studio.word_video(current, areq).exists()
        session.close()
        assert not session.folder.exists()
    finally:
        studio.close()
        ws.close()


def test_the_preview_shows_the_motion_before_its_feet_are_refined_and_the_rest_after(tiny_model, tmp_path):
    from app.studio import refinement_pending
    from app.ui.summaries import summary_markdown
    from salad.pipeline import load_pipeline

    pipe = load_pipeline(tiny_model)                         # with the planted-feet refinement (the default)
    ws = Workspace(tmp_path)
    studio = Studio(pipe, ws)
    try:
        session = studio.session(None, "client")
        req = GenerateRequest("a person walks forward", 2.0, 3, 2, 7.5, "ddim")
        result = studio.generate(session, req)
        preview = result.motion
        assert refinement_pending(result) and "foot_refine" not in preview.info
        assert studio.downloads(result) == [], "no motion files before the refinement"
        assert "refined with the full video" in summary_markdown(result)
        first_view = studio.skeleton_figure(result)
        full = studio.full_video(result)
        assert not refinement_pending(result) and result.motion is not preview and result.timings["refine_s"] > 0
        report = result.motion.info["foot_refine"]
        assert report["evaluations"] in (0, pipe.foot_refine) and "refined with the full video" not in \
            summary_markdown(result)
        stem = file_stem(req)
        assert [p.name for p in studio.downloads(result)] == [full.name, f"{stem}.bvh", f"{stem}_joints.npy",
                                                              f"{stem}_features.npy", f"{stem}.npz"]
        np.testing.assert_array_equal(np.load(result.files["npy"]), result.motion.joints.astype(np.float32))
        # the refined motion is the pipeline's own refinement of the preview's, and the 3D view follows it
        np.testing.assert_allclose(pipe.refine_feet(preview).joints, result.motion.joints, atol=1e-5)
        assert studio.skeleton_figure(result) is not first_view
        took, written = result.timings["refine_s"], result.files["npy"].stat().st_mtime_ns
        studio.refine_feet(result)                                # done once: nothing is written again
        assert result.timings["refine_s"] == took and result.files["npy"].stat().st_mtime_ns == written
        # an edit defers both of its motions
        edited = studio.edit(session, EditRequest("a person walks forward", "a person runs forward", "swap", 0.8,
                                                  (), None, 0.0, None, 2.0, 4, 2, 7.5, "ddim"))
        assert refinement_pending(edited) and studio.downloads(edited) == []
        studio.full_video(edited)
        assert not refinement_pending(edited) and len(studio.downloads(edited)) == 9
        assert "foot_refine" in edited.motion.info and "foot_refine" in edited.source.info
        # and a guided one, whose summary then gives the refined motion's path error
        creq, signal = parse_control(pipe, "a person walks forward", "path", "straight", 2.0, 1.0, None, "", "", 1.0,
                                     0, 2, 5.0, True, "ddim")
        guided = studio.control(session, creq, signal)
        assert refinement_pending(guided) and [p.name for p in studio.downloads(guided)] == [f"{file_stem(creq)}"
                                                                                            "_control.npz"]
        studio.full_video(guided)
        assert not refinement_pending(guided) and "foot_refine" in guided.motion.info
        assert guided.motion.info["control_mean_error_m"] == pytest.approx(
            control_errors(guided.motion.joints, signal).mean())
    finally:
        studio.close()
        ws.close()


def test_the_preview_comes_first_and_the_full_video_is_rendered_once(pipe, tmp_path, monkeypatch):
    import salad.render as render

    calls = []
    real = render.render_video

    def recorded(joints, path, **kwargs):
        calls.append((Path(path).name, kwargs.get("antialias", True)))
        return real(joints, path, **kwargs)

    monkeypatch.setattr(render, "render_video", recorded)
    ws = Workspace(tmp_path)
    studio = Studio(pipe, ws)
    try:
        session = studio.session(None, "client")
        req = GenerateRequest("a person walks forward", 1.0, 7, 2, 7.5, "ddim")
        result = studio.generate(session, req)
        stem = file_stem(req)
        assert calls == [(f"{stem}_preview.mp4", False)], "the preview: no antialiasing"
        assert studio.shown_video(result) == result.files["preview"] and "mp4" not in result.files
        assert [p.name for p in studio.downloads(result)] == [f"{stem}.bvh", f"{stem}_joints.npy",
                                                              f"{stem}_features.npy", f"{stem}.npz"]
        full = studio.full_video(result)
        assert calls[-1] == (f"{stem}.mp4", True) and full == result.files["mp4"] == result.folder / f"{stem}.mp4"
        # the preview is drawn at about half the pixels of the full video, and every other frame
        assert mp4_frames(result.files["preview"]).shape[:3] == (10, 320, 320)
        assert mp4_frames(full).shape[:3] == (20, 448, 448)
        assert studio.downloads(result)[0] == full and result.files["preview"] not in studio.downloads(result)
        assert result.timings["full_render_s"] > 0 and result.timings["render_s"] > 0
        # kept: neither the full video nor an identical request renders again
        assert studio.full_video(result) == full and studio.generate(session, req) is result
        assert studio.shown_video(result) == full and len(calls) == 2
        full.unlink()                                   # pruned: the request samples again
        again = studio.generate(session, req)
        assert again is not result and studio.shown_video(again) == again.files["preview"] and len(calls) == 3
        assert again.peek(("skeleton",)) is None, "the 3D figure is built on request"
    finally:
        studio.close()
        ws.close()


def test_result_cache_is_bounded(tmp_path):
    r = Result(GenerateRequest("a", None, 0, 1, 0.0, "ddim"), None, tmp_path)
    for i in range(100):
        r.cached(("k", i), lambda: i)
    assert r.cached(("k", 99), lambda: -1) == 99 and r.cached(("k", 0), lambda: -1) == -1
    assert isinstance(Session("k", tmp_path / "s").current, type(None))


def test_a_replaced_result_keeps_its_folder_until_its_render_ends(tmp_path):
    """A render into an old result's folder may still run when newer results replace it: the
    folder goes when the render ends, and no new render starts in it."""
    session = Session("k", tmp_path / "s")
    req = GenerateRequest("a", None, 0, 1, 0.0, "ddim")
    old = Result(req, None, session.new_folder())
    session.add(old)

    def render() -> Path:
        for seed in range(1, KEEP_RESULTS + 1):     # newer results arrive while this one renders
            session.add(Result(GenerateRequest("a", None, seed, 1, 0.0, "ddim"), None, session.new_folder()))
        assert old.folder.is_dir(), "the folder went while a render was writing into it"
        return atomic_write(old.folder / "video.mp4", lambda f: f.write(b"frames"))

    assert old.cached(("full video",), render).name == "video.mp4"
    assert not old.folder.exists() and not old.intact()
    with pytest.raises(ResultGone, match="replaced by newer ones"):
        old.cached(("another view",), lambda: 1)
    kept = session.latest("generate")
    assert kept.folder.is_dir() and kept.intact() and session.reuse("generate", req) is None


def test_prompt_warnings_lead_the_summary(client, pipe, tiny_dataset, monkeypatch):
    from salad.models.vocabulary import PromptCheck, build_vocabulary

    monkeypatch.setattr(pipe, "prompt_check", PromptCheck(build_vocabulary(tiny_dataset), pipe.text_encoder))
    out = generate(client, "a person does a cartwheel", seconds=1.2, seed=11, steps=3)
    first = out[2].splitlines()[0]
    assert first.startswith("⚠") and "not trained on" in first and "closest known motion" in first
    quiet = generate(client, "a person walks forward", seconds=1.2, seed=11, steps=3)
    assert "⚠" not in quiet[2]


@pytest.mark.parametrize("data, message", [
    (["a person walks", True, 1.0, 0, STEPS, 7.5, "euler", True], "sampler must be one of ddim, dpm"),
    (["a person walks", True, 1.0, 0, "many", 7.5, "ddim", True], "steps"),
    (["a person walks", True, 1.0, 0, STEPS, 7.5, "ddim"], "enough input values"),   # the foot-lock switch left out
])
def test_raw_http_clients_get_the_error_message(server, data, message):
    """What a client without gradio_client sees: the two-step /call API with server-sent events."""
    import httpx

    base = server[0].rstrip("/")
    with httpx.Client(timeout=120) as http:
        posted = http.post(f"{base}/gradio_api/call/generate", json={"data": data})
        if posted.status_code != 200:                 # refused at once: the reason is in the body
            assert message in posted.text.lower() or message in posted.text
            return
        event_id = posted.json()["event_id"]
        stream = http.get(f"{base}/gradio_api/call/generate/{event_id}").text
    assert "event: error" in stream
    payload = stream.split("event: error", 1)[1].split("data:", 1)[1].strip().splitlines()[0]
    assert payload != "null" and message in payload.lower(), payload


def test_the_full_video_brings_the_refined_motions_views_and_files(tiny_model, tmp_path):
    """Over a pipeline that refines the planted feet: the preview comes without motion files, and the
    full video's event brings the files, the 3D view and the summary of the refined motion."""
    from salad.pipeline import load_pipeline

    (tmp_path / "studio").mkdir()
    with serve_studio(load_pipeline(tiny_model), tmp_path / "studio") as (url, _):
        client = Client(url, verbose=False, download_files=str(tmp_path / "downloads"), analytics_enabled=False)
        first = generate(client, "a person walks forward", seconds=2.0, seed=3, steps=3)
        assert first[3] in (None, []), "no motion files before the refinement"
        assert "refined with the full video" in first[2]
        full, listed, skeleton, summary = client.predict("cm", api_name="/generate_video")
        assert "plot" in skeleton and "refined with the full video" not in summary and "feet refined in" in summary
        assert [Path(f).suffix for f in listed] == [".mp4", ".bvh", ".npy", ".npy", ".npz"]
        # asked again, nothing is refined on the way: the views stay
        _, _, *views = client.predict("cm", api_name="/generate_video")
        assert views == [{"__type__": "update"}] * 2


def test_a_closed_studio_leaves_no_render_worker(pipe, tmp_path):
    from salad.render import workers

    with serve_studio(pipe, tmp_path):
        workers.wait_ready(1)
        assert len(workers.running()) == 1
    for thread in threading.enumerate():        # a warm-up still under way stops what it starts once it sees the close
        if thread.name == "render-warm-up":
            thread.join(60)
    assert workers.running() == [], "closing the studio stops its render worker"
