"""The studio in a real browser: Debian's Chromium driven by Playwright against `python -m app`
on the tiny trained model. Screenshots go to test-artifacts/browser/, and also to
$SALAD_SCREENSHOTS (e.g. assets/screenshots, relative to the repository) when that is set.

To shoot the screenshots with a real model:
    SALAD_SCREENSHOTS=assets/screenshots SALAD_BROWSER_MODEL=assets/model SALAD_BROWSER_STEPS=50 \
        pytest tests/test_browser.py
"""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from conftest import free_port

JS_ALL_Z = ("Array.from(document.querySelector(PLOT)._fullData)"
            ".flatMap(t => Array.from(t.z || []).filter(v => v !== null))")

REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "test-artifacts" / "browser"
CHROMIUM = Path("/usr/bin/chromium")
# Quiet, offline Chromium: no first-run, sync, component updates or background fetches.
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--autoplay-policy=no-user-gesture-required"]
PROMPT = "a person waves their right hand happily"
STEPS = int(os.environ.get("SALAD_BROWSER_STEPS", "4"))     # sampling steps of the edit and control runs

pytestmark = pytest.mark.browser



@pytest.fixture(scope="module")
def studio_url(request, tmp_path_factory):
    """`python -m app` on a free port, as a user starts it; stopped with SIGTERM afterwards.
    The model is $SALAD_BROWSER_MODEL, else the tiny trained one."""
    model = os.environ.get("SALAD_BROWSER_MODEL") or request.getfixturevalue("tiny_model")
    port = free_port()
    logs = tmp_path_factory.mktemp("studio-log") / "studio.log"
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    with open(logs, "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "app", "--model", str(model), "--port", str(port)],
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


def shoot(target, name: str) -> None:
    """Screenshot a page or an element into the artifacts (and $SALAD_SCREENSHOTS when set)."""
    target.screenshot(path=str(ARTIFACTS / name))
    extra = os.environ.get("SALAD_SCREENSHOTS")
    if extra:
        folder = Path(extra) if Path(extra).is_absolute() else REPO / extra
        folder.mkdir(parents=True, exist_ok=True)
        target.screenshot(path=str(folder / name))


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
    shoot(page.locator("#generate-tab"), "generate.png")

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
    shoot(page.locator("#attention-tab"), "attention.png")
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


def set_slider(page, selector: str, value) -> None:
    box = page.locator(f"{selector} input[type=number]")
    box.fill(str(value))
    box.press("Enter")


def wait_for_new_video(page, selector: str, previous: str | None, width: int) -> str:
    """Wait until the <video> under `selector` shows a new file of the given width; returns its src."""
    page.wait_for_function("""([sel, prev, width]) => {
        const v = document.querySelector(sel);
        return v && v.src && v.src !== prev && v.videoWidth === width; }""", arg=[selector, previous, width])
    return page.evaluate(f"() => document.querySelector({selector!r}).src")


def settle_edit(page) -> None:
    """Before a screenshot for the docs: wait for the edit's remaining downloads to be made."""
    if os.environ.get("SALAD_SCREENSHOTS"):
        page.wait_for_function("() => document.querySelectorAll('#edit-downloads a').length >= 13")


def plot_title(page, selector: str) -> str:
    return page.evaluate(f"() => document.querySelector({selector!r}).layout.title.text")


def test_every_edit_mode_shows_source_and_edit_side_by_side(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.get_by_role("tab", name="Edit").click()
    page.locator("#edit-tab").get_by_text("Sampling", exact=True).click()
    set_slider(page, "#edit-steps", STEPS)

    src, video = None, "#edit-video video"
    source_map, edited_map = "#edit-source-heatmap .js-plotly-plot", "#edit-edited-heatmap .js-plotly-plot"
    # word swap (the panel opens on a right-to-left hand swap)
    page.locator("#edit-button").click()
    src = wait_for_new_video(page, video, src, 768)
    page.wait_for_function(f"() => {{ const g = document.querySelector({edited_map!r});"
                           " return g && g.data && g.data[0].type === 'heatmap'; }")
    assert "right" in plot_title(page, source_map) and "left" in plot_title(page, edited_map)
    assert "Word swap" in page.locator("#edit-summary").inner_text()
    page.wait_for_function("() => document.querySelectorAll('#edit-downloads a').length >= 13")
    shoot(page.locator("#edit-tab"), "edit-swap.png")

    # picking another word redraws both maps
    page.locator("#edit-word label", has_text="hand").click()
    page.wait_for_function(f"() => document.querySelector({edited_map!r}).layout.title.text.includes('hand')")

    # refine: words added to the source
    page.locator("#edit-mode label", has_text="refine").click()
    page.locator("#edit-target textarea").fill("a person waves their right hand happily and slowly")
    page.locator("#edit-button").click()
    src = wait_for_new_video(page, video, src, 768)
    page.wait_for_function("() => document.querySelector('#edit-summary').innerText.includes('Refinement')")
    settle_edit(page)
    shoot(page.locator("#edit-tab"), "edit-refine.png")

    # re-weighting: the picker offers the source's words and starts on the last one
    page.locator("#edit-mode label", has_text="re-weight").click()
    page.wait_for_function("() => document.querySelector('#edit-reweight-word input').value === 'happily'")
    page.locator("#edit-button").click()
    src = wait_for_new_video(page, video, src, 768)
    page.wait_for_function("() => document.querySelector('#edit-summary').innerText.includes('Re-weighted')")
    settle_edit(page)
    shoot(page.locator("#edit-tab"), "edit-reweight.png")

    # mirroring: the body half defaults to arms and legs
    page.locator("#edit-source textarea").fill("a person waves their left hand")
    page.locator("#edit-mode label", has_text="mirror").click()
    page.wait_for_function("() => document.querySelector('#edit-mirror input[value=all]').checked")
    page.locator("#edit-button").click()
    src = wait_for_new_video(page, video, src, 768)
    page.wait_for_function("() => document.querySelector('#edit-summary').innerText.includes('Mirrored')")
    settle_edit(page)
    shoot(page.locator("#edit-tab"), "edit-mirror.png")
    assert not page.outside_requests, f"the page reached outside hosts: {page.outside_requests[:5]}"


def test_a_path_control_shows_the_guided_motion_and_its_error(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.get_by_role("tab", name="Control").click()
    preview = "#control-preview .js-plotly-plot"
    page.wait_for_function(f"() => {{ const g = document.querySelector({preview!r});"
                           " return g && g.data && g.data.some(t => t.name === 'target'); }")
    page.locator("#control-tab").get_by_text("Sampling", exact=True).click()
    set_slider(page, "#control-steps", STEPS)
    page.locator("#control-button").click()
    wait_for_new_video(page, "#control-video video", None, 448)
    top = "#control-top-view .js-plotly-plot"
    page.wait_for_function(f"() => {{ const g = document.querySelector({top!r});"
                           " return g && g.data && g.data.some(t => t.name === 'achieved'); }")
    assert "control error: mean" in page.locator("#control-summary").inner_text()
    shoot(page.locator("#control-tab"), "control-path.png")
    assert not page.outside_requests, f"the page reached outside hosts: {page.outside_requests[:5]}"


def test_a_real_motion_upload_is_mirrored_next_to_its_input(studio_url, page, bandai_subset, tmp_path):
    import shutil

    from conftest import BANDAI_SUBSET

    bvh = tmp_path / "wave-left-hand.bvh"              # a real capture: a left-hand wave
    shutil.copy(bandai_subset / f"{BANDAI_SUBSET[2]}.bvh", bvh)
    page.goto(studio_url, wait_until="load")
    page.get_by_role("tab", name="Real motion").click()
    page.locator("#real-upload input[type=file]").set_input_files(str(bvh))
    page.locator("#real-upload").get_by_text("wave-left-hand.bvh").wait_for()
    page.locator("#real-source textarea").fill("a person waves their left hand")
    page.locator("#real-mode label", has_text="mirror").click()
    page.locator("#real-tab").get_by_text("Inversion and sampling", exact=True).click()
    set_slider(page, "#real-steps", STEPS)
    page.locator("#real-button").click()

    # input, reconstruction and edit in three panels; the video loads and plays
    wait_for_new_video(page, "#real-video video", None, 3 * 384)
    page.wait_for_function("() => { const v = document.querySelector('#real-video video');"
                           " return v && v.videoWidth > 0 && v.currentTime > 0.2; }")
    summary = page.locator("#real-summary").inner_text()
    assert "Mirroring" in summary and "wave-left-hand.bvh" in summary and "MPJPE" in summary
    page.wait_for_function("() => document.querySelectorAll('#real-downloads a').length >= 4")
    shoot(page.locator("#real-tab"), "real-mirror.png")
    assert not page.outside_requests, f"the page reached outside hosts: {page.outside_requests[:5]}"
