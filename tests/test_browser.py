"""The studio in a real browser: Debian's Chromium driven by Playwright against `python -m app`
on the tiny trained model. Screenshots go to test-artifacts/browser/."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

JS_ALL_Z = ("Array.from(document.querySelector(PLOT)._fullData)"
            ".flatMap(t => Array.from(t.z || []).filter(v => v !== null))")

REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "test-artifacts" / "browser"
CHROMIUM = Path("/usr/bin/chromium")
# Quiet, offline Chromium: no first-run, sync, component updates or background fetches.
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--autoplay-policy=no-user-gesture-required"]
PROMPT = "a person waves their right hand happily"

pytestmark = pytest.mark.browser


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def studio_url(tiny_model, tmp_path_factory):
    """`python -m app` on a free port, as a user starts it; stopped with SIGTERM afterwards."""
    port = free_port()
    logs = tmp_path_factory.mktemp("studio-log") / "studio.log"
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    with open(logs, "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "app", "--model", str(tiny_model), "--port", str(port)],
                                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/"
    try:
        deadline = time.time() + 180
        while True:
            if proc.poll() is not None or time.time() > deadline:
                pytest.fail(f"the studio did not start:\n{logs.read_text()[-3000:]}")
            try:
                if httpx.get(url, timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture
def page(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is not installed (apt install chromium)")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with sync_api.sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"), executable_path=str(CHROMIUM), headless=True, args=FLAGS,
            viewport={"width": 1400, "height": 1000})
        try:
            page = context.new_page()
            page.set_default_timeout(120_000)
            page.outside_requests = []
            page.on("request", lambda r: page.outside_requests.append(r.url)
                    if r.url.startswith("http") and not r.url.startswith("http://127.0.0.1") else None)
            yield page
        finally:
            context.close()


def video_size(page, selector: str):
    return page.evaluate(f"""() => {{
        const v = document.querySelector({selector!r});
        return v ? [v.videoWidth, v.videoHeight, v.paused, v.loop] : null; }}""")


def test_generate_then_explore_a_words_attention(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.locator("#prompt textarea").fill(PROMPT)
    page.locator("#generate-button").click()

    # The rendered MP4 loads, plays and loops.
    page.wait_for_function("() => { const v = document.querySelector('#motion-video video');"
                           " return v && v.videoWidth > 0 && v.currentTime > 0.2; }")
    width, height, paused, loop = video_size(page, "#motion-video video")
    assert (width, height) == (448, 448) and not paused and loop
    assert "happily" in page.locator("#summary").inner_text()

    # The 3D view's frame slider moves the skeleton (a click on the slider's rail near its end).
    plot = "#skeleton-plot .js-plotly-plot"
    page.wait_for_selector(plot)
    # every trace's decoded z values (plotly ships arrays base64-packed; _fullData holds them unpacked);
    # the restyle lands asynchronously after the slider moves, so wait for the values to change
    all_z = "JSON.stringify(" + JS_ALL_Z.replace("PLOT", repr(plot)) + ")"
    page.evaluate(f"() => {{ window.__zBefore = {all_z}; }}")
    assert page.evaluate("() => window.__zBefore.length > 2")
    rail = page.locator(f"{plot} .slider-rail-rect").bounding_box()
    page.mouse.click(rail["x"] + 0.9 * rail["width"], rail["y"] + rail["height"] / 2)
    page.wait_for_function(f"() => document.querySelector({plot!r}).layout.sliders[0].active > 0")
    page.wait_for_function(f"() => {all_z} !== window.__zBefore", timeout=15000)
    page.locator("#generate-tab").screenshot(path=str(ARTIFACTS / "generate.png"))

    # Pick a word: its heatmap, the tinted skeleton video and the overview of all words appear.
    page.get_by_role("tab", name="Attention").click()
    page.locator("#word-chips label", has_text="right").click()
    heatmap = "#word-heatmap .js-plotly-plot"
    page.wait_for_function(f"() => {{ const g = document.querySelector({heatmap!r});"
                           " return g && g.data && g.data[0].type === 'heatmap'; }")
    title = page.evaluate(f"() => document.querySelector({heatmap!r}).layout.title.text")
    assert "right" in title
    page.wait_for_function("() => { const v = document.querySelector('#word-video video');"
                           " return v && v.videoWidth > 0; }")
    n_panels = page.evaluate("() => document.querySelector('#attention-overview .js-plotly-plot')"
                             ".data.filter(t => t.type === 'heatmap').length")
    assert n_panels == len(PROMPT.split())
    page.locator("#attention-tab").screenshot(path=str(ARTIFACTS / "attention.png"))
    page.screenshot(path=str(ARTIFACTS / "page.png"), full_page=True)
    assert not page.outside_requests, f"the page reached outside hosts: {page.outside_requests[:5]}"


def test_bad_input_shows_a_message_and_the_page_keeps_working(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.locator("#prompt textarea").fill("a person 🕺 dances")
    page.locator("#generate-button").click()
    toast = page.get_by_text("cannot read “🕺”")
    toast.wait_for()
    page.screenshot(path=str(ARTIFACTS / "error.png"))
    page.locator("#prompt textarea").fill("someone walks and turns left")
    page.locator("#generate-button").click()
    page.wait_for_function("() => { const v = document.querySelector('#motion-video video');"
                           " return v && v.videoWidth > 0; }")
