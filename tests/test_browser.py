"""The studio in a real browser: Debian's Chromium driven by Playwright against `python -m app`
on the tiny trained model. Screenshots go to test-artifacts/browser/, and also to
$SALAD_SCREENSHOTS (e.g. assets/screenshots, relative to the repository) when that is set.

To shoot the screenshots with a real model:
    SALAD_SCREENSHOTS=assets/screenshots SALAD_BROWSER_MODEL=assets/model SALAD_BROWSER_STEPS=default \
        pytest tests/test_browser.py
(default: every tab samples with its own default steps, as a user's first click does).
"""
import os
import re
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
# sampling steps of the runs that set them (the tiny model's 4 keep the tests quick); "default": the tabs' own
STEPS = None if os.environ.get("SALAD_BROWSER_STEPS") == "default" else int(os.environ.get("SALAD_BROWSER_STEPS", "4"))

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
    """Screenshot a page or an element into the artifacts (and $SALAD_SCREENSHOTS when set, in 256
    colours, which keeps a tab's screenshot to a few hundred kB)."""
    target.screenshot(path=str(ARTIFACTS / name))
    extra = os.environ.get("SALAD_SCREENSHOTS")
    if extra:
        from PIL import Image

        folder = Path(extra) if Path(extra).is_absolute() else REPO / extra
        folder.mkdir(parents=True, exist_ok=True)
        with Image.open(ARTIFACTS / name) as shot:
            shot.convert("RGB").quantize(256, dither=Image.Dither.NONE).save(folder / name, optimize=True)


def box(page, selector: str) -> dict:
    """The bounding box of the first element matching `selector` (it must exist)."""
    found = page.locator(selector).first.bounding_box()
    assert found is not None, f"{selector} is not on the page"
    return found


def overlap(a: dict, b: dict) -> bool:
    return (a["x"] < b["x"] + b["width"] and b["x"] < a["x"] + a["width"]
            and a["y"] < b["y"] + b["height"] and b["y"] < a["y"] + a["height"])


def clipped(page, selector: str) -> list[str]:
    """The texts of elements matching `selector` whose content does not fit their box."""
    return page.evaluate("""sel => Array.from(document.querySelectorAll(sel))
        .filter(e => e.scrollHeight > e.clientHeight + 1).map(e => e.innerText)""", selector)


def video_size(page, selector: str):
    return page.evaluate(f"""() => {{
        const v = document.querySelector({selector!r});
        return v ? [v.videoWidth, v.videoHeight, v.paused, v.loop] : null; }}""")


def record_video_sources(page, selector: str) -> None:
    """Keep every src the <video> under `selector` shows, in order, in window.__srcs."""
    page.evaluate("""sel => { window.__srcs = [];
        setInterval(() => { const v = document.querySelector(sel);
            if (v && v.src && window.__srcs[window.__srcs.length - 1] !== v.src) window.__srcs.push(v.src); }, 15); }""",
                  selector)


def test_generate_then_explore_a_words_attention(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.locator("#prompt textarea").fill(PROMPT)
    record_video_sources(page, "#motion-video video")
    page.locator("#generate-button").click()

    # The preview shows first, then the antialiased MP4 takes its place and joins the downloads;
    # it loads, plays and loops.
    page.wait_for_function("() => { const v = document.querySelector('#motion-video video');"
                           " return v && v.videoWidth > 0 && v.currentTime > 0.2 && !v.src.includes('_preview'); }")
    sources = page.evaluate("() => window.__srcs")
    assert "_preview.mp4" in sources[0] and sources[-1].endswith(".mp4") and "_preview" not in sources[-1], sources
    page.wait_for_function("() => Array.from(document.querySelectorAll('#downloads .filename'))"
                           ".some(e => e.innerText.replace(/\\s/g, '').endsWith('.mp4'))")
    names = ["".join(n.split()) for n in page.locator("#downloads .filename").all_text_contents()]
    assert not any("_preview" in n for n in names), names
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


def set_steps(page, selector: str) -> None:
    """A tab's steps slider to STEPS (left at the tab's default when STEPS is None)."""
    if STEPS is not None:
        set_slider(page, selector, STEPS)


def wait_for_new_video(page, selector: str, previous: str | None, width: int) -> str:
    """Wait until the <video> under `selector` shows a new file of the given width, its full
    (antialiased) render rather than the preview shown first; returns its src."""
    page.wait_for_function("""([sel, prev, width]) => {
        const v = document.querySelector(sel);
        return v && v.src && v.src !== prev && !v.src.includes('_preview') && v.videoWidth === width; }""",
                           arg=[selector, previous, width])
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
    set_steps(page, "#edit-steps")

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
    # the picker follows the new source before the mode changes: handled the other way round (a busy
    # machine may answer the two quick events out of order), it would re-weight 'hand' in mirror mode
    reweight_word = "document.querySelector('#edit-reweight-word input').value"
    page.wait_for_function(f"() => {reweight_word} === 'hand'")
    page.locator("#edit-mode label", has_text="mirror").click()
    page.wait_for_function("() => document.querySelector('#edit-mirror input[value=all]').checked"
                           f" && ['', 'none'].includes({reweight_word})")
    page.locator("#edit-button").click()
    src = wait_for_new_video(page, video, src, 768)
    page.wait_for_function("() => document.querySelector('#edit-summary').innerText.includes('Mirrored')")
    settle_edit(page)
    shoot(page.locator("#edit-tab"), "edit-mirror.png")
    assert not page.outside_requests, f"the page reached outside hosts: {page.outside_requests[:5]}"


def test_edit_this_motion_opens_the_edit_tab_on_the_generated_motion(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.locator("#prompt textarea").fill(PROMPT)
    page.locator("#generate-tab").get_by_text("Sampling", exact=True).click()
    set_steps(page, "#steps")
    page.locator("#seed input").fill("5")
    page.locator("#generate-button").click()
    page.wait_for_function("() => document.querySelector('#summary').innerText.includes('happily')")
    page.locator("#edit-this-button").click()
    # the Edit tab shows, its source and target are the prompt, its sampling the generation's
    page.wait_for_function("""(prompt) => { const t = document.querySelector('#edit-source textarea');
        return t && t.offsetParent !== null && t.value === prompt; }""", arg=PROMPT)
    assert page.locator("#edit-target textarea").input_value() == PROMPT
    page.locator("#edit-tab").get_by_text("Sampling", exact=True).click()
    # the generation's sampler: the teacher's on the tiny model, the student's on the embedded one
    sampled = re.search(r"(\d+) (SDE-DPM-Solver\+\+|consistency) steps?", page.locator("#summary").inner_text())
    assert page.locator("#edit-steps input[type=number]").input_value() == sampled.group(1)
    assert page.locator("#edit-seed input").input_value() == "5"
    page.locator("#edit-target textarea").fill(PROMPT.replace("right", "left"))
    page.locator("#edit-button").click()
    # a teacher's generation was recorded, so the edit replays its source branch; a student's is sampled again
    said = "replayed" if sampled.group(2) != "consistency" else "Sampled both branches"
    page.wait_for_function("(said) => document.querySelector('#edit-summary').innerText.includes(said)", arg=said)
    assert "“right” → “left”" in page.locator("#edit-summary").inner_text()


def test_a_path_control_shows_the_guided_motion_and_its_error(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.get_by_role("tab", name="Control").click()
    preview = "#control-preview .js-plotly-plot"
    page.wait_for_function(f"() => {{ const g = document.querySelector({preview!r});"
                           " return g && g.data && g.data.some(t => t.name === 'target'); }")
    page.locator("#control-tab").get_by_text("Sampling", exact=True).click()
    set_steps(page, "#control-steps")
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
    set_steps(page, "#real-steps")
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


def legend_entries(page, plot: str) -> list[str]:
    """The legend entries of a Plotly figure that lie inside the figure's area."""
    return page.evaluate("""sel => {
        const g = document.querySelector(sel), area = g.getBoundingClientRect();
        return Array.from(g.querySelectorAll('.legend .traces')).filter(t => {
            const b = t.getBoundingClientRect();
            return b.top >= area.top && b.bottom <= area.bottom && b.left >= area.left - 1 && b.right <= area.right + 1;
        }).map(t => t.textContent); }""", plot)


def test_at_800_px_the_views_are_wide_framed_and_nothing_overlaps(studio_url, page):
    page.set_viewport_size({"width": 800, "height": 1000})
    page.goto(studio_url, wait_until="load")
    page.locator("#prompt textarea").fill("a person walks forward")
    page.locator("#generate-button").click()
    wait_for_new_video(page, "#motion-video video", None, 448)     # the full video, after the preview
    plot = "#skeleton-plot .js-plotly-plot"
    page.wait_for_function(f"() => {{ const g = document.querySelector({plot!r}); return g && g.data; }}")
    page.wait_for_timeout(500)      # the figure is drawn a moment after its data arrives
    # the results sit under the controls: the video and the 3D view share the full width
    video, view = box(page, "#motion-video video"), box(page, plot)
    assert video["width"] >= 300 and view["width"] >= 300 and not overlap(video, view)
    # the 3D view: every legend entry shown, the box around the body (2.2 m), moving with it
    assert len(legend_entries(page, plot)) == 8
    ranges = "JSON.stringify(document.querySelector(PLOT).layout.scene.xaxis.range)".replace("PLOT", repr(plot))
    x0, x1 = page.evaluate(f"() => {ranges}").strip("[]").split(",")
    assert abs(float(x1) - float(x0) - 2.2) < 1e-6
    page.evaluate(f"() => {{ window.__rangeBefore = {ranges}; }}")
    page.locator(f"{plot} .slider-rail-rect").scroll_into_view_if_needed()     # below the fold at this width
    rail = page.locator(f"{plot} .slider-rail-rect").bounding_box()
    page.mouse.click(rail["x"] + 0.95 * rail["width"], rail["y"] + rail["height"] / 2)
    page.wait_for_function(f"() => document.querySelector({plot!r}).layout.sliders[0].active > 0")
    page.wait_for_function(f"() => {ranges} !== window.__rangeBefore", timeout=15000)
    # captions above the views are whole; the downloads tell joints from features at a glance
    assert not clipped(page, "#generate-tab .video-caption")
    names = page.locator("#downloads .filename").all_text_contents()
    assert any("".join(n.split()).endswith("_joints.npy") for n in names)
    assert any("".join(n.split()).endswith("_features.npy") for n in names)
    direction = page.evaluate("() => getComputedStyle(document.querySelector('#downloads .stem')).direction")
    assert direction == "rtl", "long names are shortened at the start, keeping _joints / _features"
    shoot(page.locator("#generate-tab"), "generate-800.png")

    # the Edit tab: its caption whole, the remaining downloads' progress off the file list
    page.get_by_role("tab", name="Edit").click()
    page.locator("#edit-tab").get_by_text("Sampling", exact=True).click()
    set_steps(page, "#edit-steps")
    # where the rendering progress shows while the edit's remaining downloads are made (a brief
    # "processing" timer may flash on every output as a result arrives; the bar is what covered the files)
    page.evaluate("""() => { window.__progressIn = new Set();
        new MutationObserver(() => { for (const id of ['edit-downloads', 'edit-files-status'])
            if (Array.from(document.querySelectorAll(`#${id} .progress-level, #${id} .progress-text`))
                    .some(e => e.classList.contains('progress-level') || e.innerText.includes('rendering')))
                window.__progressIn.add(id); })
        .observe(document.body, {subtree: true, childList: true, attributes: true, characterData: true}); }""")
    page.locator("#edit-button").click()
    wait_for_new_video(page, "#edit-video video", None, 768)
    assert box(page, "#edit-video video")["width"] >= 600
    assert not clipped(page, "#edit-tab .video-caption")
    page.wait_for_function("() => document.querySelectorAll('#edit-downloads a').length >= 13")
    assert not overlap(box(page, "#edit-files-status"), box(page, "#edit-downloads"))
    assert "edit-downloads" not in page.evaluate("() => Array.from(window.__progressIn)"), \
        "no progress bar over the file list"
    shoot(page.locator("#edit-tab"), "edit-800.png")
    assert not page.outside_requests, f"the page reached outside hosts: {page.outside_requests[:5]}"


def test_at_phone_width_the_3d_view_keeps_its_legend(studio_url, page):
    page.set_viewport_size({"width": 400, "height": 900})
    page.goto(studio_url, wait_until="load")
    page.locator("#prompt textarea").fill("someone walks and turns left")
    page.locator("#generate-button").click()
    # measured once the chained full-video event has answered: it may draw the 3D view again
    wait_for_new_video(page, "#motion-video video", None, 448)
    plot = "#skeleton-plot .js-plotly-plot"
    page.wait_for_function(f"() => {{ const g = document.querySelector({plot!r}); return g && g.data; }}")
    page.wait_for_timeout(500)
    view = box(page, plot)
    assert view["x"] >= 0 and view["x"] + view["width"] <= 400 and view["width"] >= 300
    assert len(legend_entries(page, plot)) == 8
    shoot(page.locator("#skeleton-plot"), "3d-view-phone.png")


def test_a_clamped_number_and_a_cut_prompt_are_said_at_once(studio_url, page):
    page.goto(studio_url, wait_until="load")
    page.locator("#generate-tab").get_by_text("Automatic length").click()
    seconds = page.locator("#seconds input[type=number]")
    longest = page.evaluate("() => document.querySelector('#seconds input[type=range]').max")
    seconds.fill("1000")
    seconds.press("Enter")
    note = page.locator("#seconds .salad-note")
    note.wait_for()
    assert "1000" in note.inner_text() and f"set to {longest}" in note.inner_text()
    assert seconds.input_value() == longest, "the box shows the value that is used"
    shoot(page.locator("#seconds"), "clamp-note.png")
    seconds.fill("2")
    seconds.press("Enter")
    note.wait_for(state="detached")
    # a number box's limits too: the seed
    page.locator("#generate-tab").get_by_text("Sampling", exact=True).click()
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    seed = page.locator("#seed input[type=number]")
    seed.wait_for()
    # The accordion mounts its boxes when it opens and may write their value once more after they appear; on a
    # loaded machine that can land between the typing and Enter (the box then holds 0, in range, and no note is
    # due). Such a lost keystroke is typed again; the note itself must still come from Enter on -5.
    for _ in range(3):
        seed.fill("-5")
        seed.press("Enter")
        try:
            page.locator("#seed .salad-note").wait_for(timeout=10_000)
            break
        except PlaywrightTimeout:
            continue
    else:
        pytest.fail(f"no note under the seed box after Enter on -5 (three tries); it holds {seed.input_value()!r}")
    assert seed.input_value() == "0" and "set to 0" in page.locator("#seed .salad-note").inner_text()
    # the prompt box takes 300 characters: a longer paste is cut, and the page says so
    page.evaluate("""() => { const a = document.querySelector('#prompt textarea'); a.focus();
        const data = new DataTransfer(); data.setData('text', 'a person walks forward '.repeat(20));
        a.dispatchEvent(new ClipboardEvent('paste', {clipboardData: data, bubbles: true, cancelable: true})); }""")
    cut = page.locator("#prompt .salad-note")
    cut.wait_for()
    assert "limited to 300 characters" in cut.inner_text() and "160 pasted characters were cut" in cut.inner_text()


def test_a_bad_upload_is_reported_when_it_is_uploaded(studio_url, page, tmp_path):
    import numpy as np

    np.save(tmp_path / "not-a-motion.npy", np.zeros((40, 5), dtype=np.float32))
    page.goto(studio_url, wait_until="load")
    page.get_by_role("tab", name="Real motion").click()
    page.locator("#real-upload input[type=file]").set_input_files(str(tmp_path / "not-a-motion.npy"))
    toast = page.get_by_text("not-a-motion.npy: expected joints (T, 22, 3)")
    toast.first.wait_for(timeout=30000)
    # a prompt the encoder cannot read: the message shows its characters (a CJK font is installed)
    page.get_by_role("tab", name="Generate").click()
    page.locator("#prompt textarea").fill("一个人在走路")
    page.locator("#generate-button").click()
    page.get_by_text("cannot read “一个人在走路”").first.wait_for()
    page.screenshot(path=str(ARTIFACTS / "upload-and-cjk-errors.png"))
