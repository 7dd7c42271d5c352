import json
import shutil
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from salad.motion import skeleton as sk
from salad.render import (
    attention_heatmap, attention_overview, attention_png, gl_backend, last_render_stats, render_frames,
    render_side_by_side, render_video, save_frame_strip, save_gif, skeleton_figure,
    skeleton_figure_spec,
)
from salad.render import camera as cam
from tests.conftest import synthetic_walk

SIZE = (160, 160)


def saturated(frames: np.ndarray, threshold: int = 70) -> np.ndarray:
    """Pixels with a strong hue: the floor, background and shadow are near-grey, the limbs are not."""
    f = frames.astype(np.int16)
    return (f.max(-1) - f.min(-1)) > threshold


@pytest.fixture(scope="module")
def walk():
    return synthetic_walk(24, turn=0.4)


def read_video(path):
    reader = imageio.get_reader(path, format="FFMPEG")
    try:
        frames = np.stack([f for f in reader.iter_data()])
        meta = reader.get_meta_data()
    finally:
        reader.close()
    return frames, meta


# ------------------------------------------------------------------ video

def test_video_round_trip(tmp_path, walk):
    calls = []
    out = render_video(walk, tmp_path / "walk.mp4", size=SIZE, title="a person walks",
                       progress=lambda done, total: calls.append((done, total)))
    assert out == tmp_path / "walk.mp4" and out.stat().st_size > 1000
    frames, meta = read_video(out)
    assert frames.shape == (len(walk), SIZE[1], SIZE[0], 3)
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert abs(meta["fps"] - 20) < 1e-6
    assert frames.std() > 10, "frames are not uniform"
    limbs = saturated(frames)
    assert limbs.sum(axis=(1, 2)).min() > 30, "every frame shows the coloured skeleton"
    changed = (limbs[0] ^ limbs[12]).sum()
    assert changed > 20, "the skeleton moves between frames"
    assert calls == [(i + 1, len(walk)) for i in range(len(walk))]
    assert gl_backend() in ("egl", "osmesa")
    stats = last_render_stats()
    assert stats["frames"] == len(walk) and stats["backend"] == gl_backend()


def test_skeleton_colours_follow_body_parts(walk):
    frame = render_frames(walk[:1], size=(256, 256))[0].astype(int)
    # Left limbs are drawn in blues, right limbs in reds/oranges.
    blue = (frame[..., 2] - frame[..., 0] > 60).sum()
    red = (frame[..., 0] - frame[..., 2] > 60).sum()
    assert blue > 40 and red > 40


def test_title_and_tint_change_pixels(walk):
    plain = render_frames(walk[:3], size=SIZE)
    titled = render_frames(walk[:3], size=SIZE, title="waves")
    top = slice(0, SIZE[1] // 6)
    assert np.abs(plain[:, top].astype(int) - titled[:, top]).mean() > 1
    assert np.array_equal(plain[:, SIZE[1] // 3:], titled[:, SIZE[1] // 3:]), "title only touches the top"
    tint = np.zeros((3, sk.NUM_JOINTS))
    tint[:, sk.PART_OF_JOINT == 5] = 1.0  # right arm fully attended
    tinted = render_frames(walk[:3], size=SIZE, tint=tint)
    body = saturated(plain) | saturated(tinted)
    assert np.abs(plain[body].astype(int) - tinted[body]).mean() > 20


def test_cjk_text_is_drawn_in_a_cjk_font_when_one_is_installed():
    from salad.render.overlay import _CJK_FONTS, font, text_font

    assert text_font("a person waves", "bold", 20) is font("bold", 20)
    if not any(path.is_file() for path in _CJK_FONTS):
        pytest.skip("no CJK font installed (apt install fonts-wqy-zenhei)")
    cjk = text_font("挥手 a person waves", "bold", 20)
    # a font without the glyphs draws both characters as the same box
    wave, hand = (np.asarray(cjk.getmask(c)) for c in "挥手")
    assert wave.shape != hand.shape or (wave != hand).any()


def test_rendering_is_repeatable_across_calls(walk):
    first = render_frames(walk[:4], size=SIZE)
    tg = walk[:4] + 0.2
    mask = np.zeros((4, sk.NUM_JOINTS), bool)
    mask[:, [0, 20]] = True
    render_frames(walk[:4][::-1].copy(), size=(96, 128), targets=tg, target_mask=mask, trajectory=walk[:, 0])
    again = render_frames(walk[:4], size=SIZE)
    assert np.array_equal(first, again), "state from another render leaked into this one"


def test_targets_are_drawn(walk):
    t = len(walk)
    targets = np.zeros((t, sk.NUM_JOINTS, 3))
    mask = np.zeros((t, sk.NUM_JOINTS), bool)
    targets[10, 20] = walk[10, 20] + np.array([0.2, 0.35, 0.0])  # left wrist keyframe, camera side
    mask[10, 20] = True
    plain = render_frames(walk[8:13], size=(256, 256))
    marked = render_frames(walk[8:13], size=(256, 256), targets=targets[8:13], target_mask=mask[8:13])
    green = lambda f: ((f[..., 1].astype(int) - np.maximum(f[..., 0], f[..., 2])) > 35).sum(axis=(1, 2))
    assert (green(plain) == 0).all()
    g = green(marked)
    assert g[2] > g[0] > 0, "the keyframe shows as a dot on every frame and as a marker on its own"


def test_camera_keeps_a_long_walk_in_view():
    walk = synthetic_walk(100, speed=1.5)  # travels 7.5 m
    assert np.linalg.norm(walk[-1, 0, [0, 2]] - walk[0, 0, [0, 2]]) > 5
    path = cam.follow_camera([walk], fps=20)[0]
    px = path.project(walk.astype(np.float64), *SIZE)
    assert (px[..., 2] > 0).all()
    assert px[..., 0].min() > 0 and px[..., 0].max() < SIZE[0]
    assert px[..., 1].min() > 0 and px[..., 1].max() < SIZE[1]
    frames = render_frames(walk[::33], size=SIZE)
    for f in saturated(frames):
        ys, xs = np.nonzero(f)
        assert len(xs) > 30
        assert xs.min() > 2 and xs.max() < SIZE[0] - 3 and ys.min() > 2 and ys.max() < SIZE[1] - 3


def test_side_by_side(tmp_path, walk):
    short = walk[:12] + np.array([0.0, 0.0, 0.5], dtype=np.float32)
    out = render_side_by_side([walk, short], ["source", "edited"], tmp_path / "pair.mp4", size=SIZE)
    frames, _ = read_video(out)
    assert frames.shape == (len(walk), SIZE[1], 2 * SIZE[0], 3)
    left, right = frames[..., :SIZE[0], :], frames[..., SIZE[0]:, :]
    assert saturated(left).sum(axis=(1, 2)).min() > 30 and saturated(right).sum(axis=(1, 2)).min() > 30
    # Labels: dark text on a light plate in each panel's top-left corner.
    corner = lambda half: (half[:, :SIZE[1] // 8, :SIZE[0] // 3].max(-1) < 90).sum(axis=(1, 2))
    assert corner(left).min() > 10 and corner(right).min() > 10
    # The shorter motion holds its last frame while the other keeps moving (codec noise aside).
    held = np.abs(right[-1].astype(int) - right[-4]).mean()
    moving = np.abs(left[-1].astype(int) - left[-4]).mean()
    assert held < 1.0 < moving


def test_side_by_side_reuses_an_unchanged_panel(tmp_path, walk):
    from salad.render import video

    other = walk * np.array([-1.0, 1.0, 1.0], dtype=np.float32)      # the same walk, mirrored
    video.panel_cache.clear()
    fresh = render_side_by_side([walk, other], ["source", "edited"], tmp_path / "fresh.mp4", size=SIZE)
    assert last_render_stats()["reused_panels"] == 0 and len(video.panel_cache) == 2
    video.panel_cache.clear()
    render_side_by_side([walk, walk[:20]], ["source", "edited"], tmp_path / "first.mp4", size=SIZE)
    again = render_side_by_side([walk, other], ["source", "edited"], tmp_path / "again.mp4", size=SIZE)
    assert last_render_stats()["reused_panels"] == 1, "the unchanged source panel is not drawn again"
    assert again.read_bytes() == fresh.read_bytes(), "a reused panel looks exactly like a drawn one"
    # A different label (or camera, size, motion) is a different panel.
    render_side_by_side([walk, other], ["before", "edited"], tmp_path / "relabelled.mp4", size=SIZE)
    assert last_render_stats()["reused_panels"] == 1
    cache = video.PanelCache(limit_bytes=1000)
    cache.put("big", np.zeros((10, 10, 10, 3), np.uint8))
    assert cache.get("big") is None, "panels over the limit are not kept"


def test_preview_renders_without_multisampling(tmp_path, walk):
    from salad.render import video

    smooth = render_frames(walk, size=SIZE)
    assert last_render_stats()["msaa_samples"] == 4
    rough = render_frames(walk, size=SIZE, antialias=False)
    assert last_render_stats()["msaa_samples"] == 0
    assert rough.shape == smooth.shape
    diff = np.abs(rough.astype(np.int16) - smooth.astype(np.int16)).max(-1)
    # only edges change: a few percent of the pixels, by a visible amount
    assert 0.001 < (diff > 24).mean() < 0.15
    np.testing.assert_array_equal(render_frames(walk, size=SIZE), smooth)   # and the next render is smooth again
    # a preview panel is never reused for the antialiased render, nor the other way round
    video.panel_cache.clear()
    render_side_by_side([walk, walk[:20]], ["a", "b"], tmp_path / "p.mp4", size=SIZE, antialias=False)
    render_side_by_side([walk, walk[:20]], ["a", "b"], tmp_path / "f.mp4", size=SIZE)
    assert last_render_stats()["reused_panels"] == 0


def test_camera_zoom_snaps_outwards():
    a = synthetic_walk(40)
    b = a.copy()
    b[:, 20, 0] += 0.01                                                # a hand moves a centimetre
    ca, cb = cam.follow_camera([a], 20), cam.follow_camera([a, b], 20)
    np.testing.assert_array_equal(ca[0].poses, cb[0].poses)
    distance = np.linalg.norm(ca[0].eyes - ca[0].targets, axis=1)
    assert np.allclose(distance / cam.DISTANCE_STEP, np.round(distance / cam.DISTANCE_STEP))


def test_gif_and_frame_strip(tmp_path, walk):
    gif = save_gif(walk[:10], tmp_path / "walk.gif", size=(96, 96), stride=2)
    frames = imageio.mimread(gif)
    assert len(frames) == 5 and frames[0].shape[:2] == (96, 96)
    strip = save_frame_strip(walk, tmp_path / "strip.png", n=4, size=(80, 96))
    img = imageio.imread(strip)
    assert img.shape[:2] == (96, 4 * 80 + 3 * 2)
    pre = render_frames(walk[:6], size=(64, 64))
    assert imageio.imread(save_frame_strip(pre, tmp_path / "pre.png", n=3)).shape[:2] == (64, 3 * 64 + 4)


# ------------------------------------------------------------------ inputs and files

@pytest.mark.parametrize("bad, message", [
    (np.zeros((10, 21, 3)), "shape"),
    (np.zeros((10, 22)), "shape"),
    (np.zeros((0, 22, 3)), "empty"),
    (np.full((5, 22, 3), np.nan), "NaN"),
    ([["a"]], "numeric"),
])
def test_bad_motions_are_rejected(tmp_path, bad, message):
    with pytest.raises(ValueError, match=message):
        render_video(bad, tmp_path / "x.mp4")
    assert list(tmp_path.iterdir()) == []


def test_bad_options_are_rejected(tmp_path, walk):
    t = len(walk)
    with pytest.raises(ValueError, match="tint"):
        render_frames(walk, tint=np.zeros((t, 7)))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        render_frames(walk, tint=np.full((t, 22), 2.0))
    with pytest.raises(ValueError, match="together"):
        render_frames(walk, targets=np.zeros((t, 22, 3)))
    with pytest.raises(ValueError, match="target_mask"):
        render_frames(walk, targets=np.zeros((t, 22, 3)), target_mask=np.zeros((t, 21), bool))
    with pytest.raises(ValueError, match="size"):
        render_frames(walk, size=(8, 8))
    with pytest.raises(ValueError, match=".mp4"):
        render_video(walk, tmp_path / "x.avi")
    with pytest.raises(ValueError, match="does not exist"):
        render_video(walk, tmp_path / "missing" / "x.mp4")
    with pytest.raises(ValueError, match="labels"):
        render_side_by_side([walk, walk], ["one"], tmp_path / "x.mp4")
    with pytest.raises(ValueError, match="list"):
        render_side_by_side(walk, ["one"], tmp_path / "x.mp4")
    with pytest.raises(ValueError, match=r"motions\[1\]"):
        render_side_by_side([walk, walk[:, :5]], ["a", "b"], tmp_path / "x.mp4")
    with pytest.raises(ValueError, match="cmap"):
        render_frames(walk[:2], tint=np.zeros((2, 22)), cmap="no-such-map")


def test_writes_are_atomic(tmp_path, walk):
    out = tmp_path / "clip.mp4"
    render_video(walk[:5], out, size=(64, 64))
    before = out.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]

    def fail(done, total):
        if done == 3:
            raise RuntimeError("cancelled")

    with pytest.raises(RuntimeError, match="cancelled"):
        render_video(walk, out, size=(64, 64), progress=fail)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"], "no temporary file left behind"
    assert out.read_bytes() == before, "a failed render does not touch the previous file"
    # The renderer is still usable after an aborted render.
    assert render_frames(walk[:2], size=(64, 64)).shape == (2, 64, 64, 3)


def test_renders_from_another_thread(walk):
    """Gradio runs handlers in worker threads: the GL context must move between threads."""
    import threading

    here = render_frames(walk[:3], size=(64, 64))
    result = {}

    def job():
        try:
            result["frames"] = render_frames(walk[:3], size=(64, 64))
        except Exception as exc:  # surfaced by the assertion below
            result["error"] = exc

    worker = threading.Thread(target=job)
    worker.start()
    worker.join(60)
    assert "error" not in result, result.get("error")
    assert np.array_equal(result["frames"], here)


def test_backend_choice(monkeypatch):
    from salad.render import backend

    chosen = gl_backend()
    assert chosen in ("egl", "osmesa") and backend.backend_reason()
    monkeypatch.setattr(backend, "_backend", None)
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    assert gl_backend() == "osmesa", "a user-set platform wins"
    monkeypatch.setattr(backend, "_backend", None)
    monkeypatch.setenv("PYOPENGL_PLATFORM", "glx")
    with pytest.raises(RuntimeError, match="headless"):
        gl_backend()
    monkeypatch.setattr(backend, "_backend", None)
    monkeypatch.delenv("PYOPENGL_PLATFORM")
    assert gl_backend() == chosen, "once OpenGL is bound, the bound platform is reported"
    monkeypatch.setattr(backend, "_backend", chosen)


def test_osmesa_fallback_renders_in_a_fresh_process():
    """When EGL does not work the renderer falls back to OSMesa, and OSMesa renders without
    recompiling shaders every frame (pyrender's cache misses there)."""
    code = (
        "import os, sys; sys.path.insert(0, {repo!r})\n"
        "os.environ.pop('PYOPENGL_PLATFORM', None)\n"
        "from salad.render import backend, engine, gl_backend, render_frames\n"
        "from tests.conftest import synthetic_walk\n"
        "backend._probe_egl = lambda: (False, 'EGL disabled for the test')\n"
        "assert gl_backend() == 'osmesa' and os.environ['PYOPENGL_PLATFORM'] == 'osmesa'\n"
        "f = render_frames(synthetic_walk(4), size=(64, 64))\n"
        "assert f.shape == (4, 64, 64, 3) and f.std() > 5\n"
        "n = len(engine._engine.renderer._program_cache._program_cache)\n"
        "render_frames(synthetic_walk(6), size=(64, 64))\n"
        "assert len(engine._engine.renderer._program_cache._program_cache) == n <= 3, n\n"
    ).format(repo=str(Path(__file__).resolve().parents[1]))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


# ------------------------------------------------------------------ figures

def test_skeleton_figure(walk):
    fig = skeleton_figure(walk, fps=20, title="walk")
    assert len(fig.frames) == len(walk)
    names = [t.name for t in fig.data]
    assert {"floor", "skeleton", "left lower", "right upper", "head"} <= set(names)
    assert fig.layout.scene.zaxis.title.text.startswith("y (m)")
    assert fig.layout.scene.aspectmode == "manual"
    assert len(fig.layout.sliders[0].steps) == len(walk)
    assert [b.label for b in fig.layout.updatemenus[0].buttons] == ["▶ play", "❚❚ pause"]
    # Frame 5 carries frame 5's coordinates (plot axes are forward, left, up).
    xs = np.array(fig.frames[5].data[0].x, dtype=float)
    assert np.nanmax(xs) == pytest.approx(walk[5, :, 2].max(), abs=1e-5)
    zs = np.array(fig.frames[5].data[0].z, dtype=float)
    assert np.nanmax(zs) == pytest.approx(walk[5, :, 1].max(), abs=1e-5)
    with pytest.raises(ValueError):
        skeleton_figure(walk[:, :3])
    # The plain spec (what the studio sends) is valid JSON (None, not NaN, at the polyline's breaks)
    # and passes plotly's validation, which skeleton_figure skips.
    import plotly.graph_objects as go

    spec = skeleton_figure_spec(walk, fps=20, title="walk")
    assert json.loads(json.dumps(spec, allow_nan=False))["frames"][5]["name"] == "5"
    assert go.Figure(spec).to_plotly_json()["layout"]["scene"]["aspectmode"] == "manual"
    with pytest.raises(ValueError):
        skeleton_figure_spec(walk, fps=0)


def test_skeleton_figure_follows_the_body(walk):
    """The default view is a 2.2 m box centred on the root that each frame moves along (plot x, y are
    the data's z, x); "path" keeps one box around the whole motion."""
    from salad.render.figures import BODY_BOX

    far = walk.copy()
    far[..., 2] += np.linspace(0, 10, len(walk))[:, None]        # a 10 m walk
    fig = skeleton_figure(far, fps=20)
    for k in (0, len(far) - 1):
        scene = fig.frames[k].layout.scene
        x0, x1 = scene.xaxis.range
        y0, y1 = scene.yaxis.range
        assert x1 - x0 == pytest.approx(BODY_BOX) and y1 - y0 == pytest.approx(BODY_BOX)
        assert (x0 + x1) / 2 == pytest.approx(far[k, 0, 2], abs=1e-5)
        assert (y0 + y1) / 2 == pytest.approx(far[k, 0, 0], abs=1e-5)
    assert tuple(fig.layout.scene.xaxis.range) == tuple(fig.frames[0].layout.scene.xaxis.range)
    # every part of the legend, the slider ticking only its labelled steps
    assert len([t for t in fig.data if t.showlegend is not False]) == 8
    assert fig.layout.sliders[0].minorticklen == 0
    whole = skeleton_figure(far, fps=20, view="path")
    x0, x1 = whole.layout.scene.xaxis.range
    assert x1 - x0 > 10 and whole.frames[5].layout.scene.xaxis.range is None
    with pytest.raises(ValueError, match="view"):
        skeleton_figure(far, view="close-up")


def test_attention_figures(tmp_path):
    rng = np.random.default_rng(0)
    att = rng.random((4, 7, 30))
    words = ["a", "person", "waves", "hands"]
    hm = attention_heatmap(att[2], "waves", fps=20)
    trace = hm.data[0]
    assert trace.type == "heatmap" and np.shape(trace.z) == (7, 30)
    assert list(trace.y) == ["root", "left lower", "right lower", "spine",
                             "left upper", "right upper", "head"]
    assert trace.x[-1] == pytest.approx(29 / 20)
    assert hm.layout.xaxis.title.text == "time (s)" and "waves" in hm.layout.title.text
    ov = attention_overview(att, words, fps=20)
    assert len(ov.data) == 4 and all(t.coloraxis == "coloraxis" for t in ov.data)
    assert ov.layout.coloraxis.cmax == pytest.approx(att.max())
    png = attention_png(att, words, tmp_path / "att.png")
    img = imageio.imread(png)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 300
    with pytest.raises(ValueError, match="words"):
        attention_overview(att, words[:3])
    with pytest.raises(ValueError, match="shape"):
        attention_heatmap(att[0, :5], "a")
    with pytest.raises(ValueError, match="NaN"):
        attention_heatmap(np.full((7, 5), np.nan), "a")


# ------------------------------------------------------------------ browser

@pytest.mark.browser
def test_mp4_plays_in_chromium(tmp_path, walk):
    chromium = shutil.which("chromium")
    sync_api = pytest.importorskip("playwright.sync_api")
    if chromium is None:
        pytest.skip("chromium is not installed")
    render_video(walk, tmp_path / "walk.mp4", size=SIZE)
    (tmp_path / "page.html").write_text(
        '<video id="v" src="walk.mp4" muted playsinline></video>')
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=[
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--autoplay-policy=no-user-gesture-required"])
        try:
            page = browser.new_page()
            page.goto((tmp_path / "page.html").as_uri())
            page.wait_for_function("document.getElementById('v').readyState >= 2", timeout=20000)
            info = page.evaluate("""async () => {
                const v = document.getElementById('v');
                await v.play();
                await new Promise(r => setTimeout(r, 400));
                return {w: v.videoWidth, h: v.videoHeight, d: v.duration, t: v.currentTime, err: v.error};
            }""")
        finally:
            browser.close()
    assert info["err"] is None
    assert (info["w"], info["h"]) == SIZE
    assert info["d"] == pytest.approx(len(walk) / 20, abs=0.06)
    assert info["t"] > 0
