"""The studio's choice of the consistency-distilled student ("fast", 4 steps) against the 50-step
teacher ("quality"), through the API (gradio_client) on the tiny trained model with a student:
generation, editing, guided control and real-motion edits with sampler "consistency", the steps
default that follows the sampler, and a studio over a model without a student, which neither
offers nor accepts it."""
import logging
from pathlib import Path

import app  # noqa: F401  (switches analytics and hub look-ups off before gradio is imported)
import numpy as np
import pytest
from gradio_client import Client, handle_file
from gradio_client.exceptions import AppError

from salad.motion.bvh import save_bvh
from salad.pipeline import DEFAULT_STEPS

from app.settings import Settings
from app.studio import Studio
from app.ui.layout import build_studio
from app.validation import parse_control, parse_real_edit
from app.workspace import Workspace
from conftest import serve_studio, synthetic_walk

STEPS = 2           # student steps for the runs below (its default is 4)
CFG = 5.0           # inside the tiny student's guidance range (2..8)
SOURCE = "a person waves their right hand happily"
TARGET = "a person waves their left hand happily"
NO_STUDENT = "has no consistency student"


@pytest.fixture(scope="module")
def student_pipe(tiny_student):
    """Without the planted-feet refinement, so that a result's motion files come with its preview
    (the studio's deferred refinement has its own test in test_app); recorded fit for guided control
    alone, so the studio's default starts the Control panel on it and the text panels on the teacher."""
    from salad.pipeline import load_pipeline

    pipe = load_pipeline(tiny_student)
    pipe.set_foot_refine(0)
    pipe.student_info["default_for"] = ["control"]
    return pipe


@pytest.fixture(scope="module")
def server(student_pipe, tmp_path_factory):
    with serve_studio(student_pipe, tmp_path_factory.mktemp("studio")) as served:
        yield served


@pytest.fixture(scope="module")
def plain_server(pipe, tmp_path_factory):
    """A studio over the tiny model without a student."""
    with serve_studio(pipe, tmp_path_factory.mktemp("plain-studio")) as served:
        yield served


@pytest.fixture
def plain_client(plain_server, tmp_path):
    return Client(plain_server[0], verbose=False, download_files=str(tmp_path), analytics_enabled=False)


@pytest.fixture(scope="module")
def walk_bvh(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("uploads") / "walk.bvh"
    save_bvh(path, synthetic_walk(33, seed=2), fps=20)
    return path


def generate(client, prompt="a person walks forward", seconds=1.2, seed=0, steps=STEPS, cfg=CFG,
             sampler="consistency"):
    return client.predict(prompt, False, seconds, seed, steps, cfg, sampler, True, api_name="/generate")


def edit(client, seed=0, steps=STEPS, sampler="consistency"):
    return client.predict(SOURCE, "swap", TARGET, None, "", 2.0, "none", 0.2, "auto", False, 1.2, seed, steps, CFG,
                          sampler, True, api_name="/edit")


def control(client, seed=0, steps=STEPS, sampler="consistency"):
    return client.predict("a person walks forward", "path", "circle", 1.2, 1.0, None, "", "first, last", 3.0, seed,
                          steps, CFG, True, sampler, api_name="/control")


def edit_real(client, upload, inversion="negative", steps=STEPS, sampler="consistency", seed=0):
    return client.predict(upload, "", "a person walks forward", "mirror", "", "", 2.0, "all", inversion, steps, CFG,
                          True, sampler, seed, api_name="/edit_real")


def joints_of(files) -> np.ndarray:
    return np.load(next(f for f in files if f.endswith("_joints.npy") and "source" not in Path(f).name))


def props(demo) -> dict:
    return {c["props"].get("elem_id"): c["props"] for c in demo.config["components"] if c["props"].get("elem_id")}


# ---------------------------------------------------------------- with a student

def test_generate_with_the_student(client, student_pipe):
    video, _, summary, files, words, *_ = generate(client, seed=3)
    assert Path(video).stat().st_size > 0 and "seed 3, 2 consistency steps (distilled student), CFG 5" in summary
    expected = student_pipe.generate("a person walks forward", seconds=1.2, seed=3, steps=STEPS, cfg=CFG,
                                     sampler="consistency")
    np.testing.assert_allclose(joints_of(files), expected.joints, atol=1e-3)
    assert [c[0] for c in words["choices"]] == ["a", "person", "walks", "forward"], "the student's attention maps"


def test_edit_with_the_student(client, student_pipe):
    video, summary, word, _, _, files = edit(client, seed=1)
    assert Path(video).stat().st_size > 0 and "Word swap" in summary
    assert "2 consistency steps (distilled student)" in summary
    expected = student_pipe.edit(SOURCE, TARGET, mode="swap", seed=1, seconds=1.2, steps=STEPS, cfg=CFG,
                                 sampler="consistency")
    edited = np.load(next(f for f in files if f.endswith("_edited_joints.npy")))
    np.testing.assert_allclose(edited, expected.edited.joints, atol=1e-3)


def test_control_with_the_student(client):
    video, top_view, summary, files = control(client, seed=2)
    assert Path(video).stat().st_size > 0 and top_view["type"] == "plotly"
    assert "Pelvis path" in summary and "control error: mean" in summary
    assert "2 consistency steps (distilled student)" in summary
    assert joints_of(files).shape == (24, 22, 3)
    _, _, ddim_summary, _ = control(client, seed=2, steps=3, sampler="ddim")
    assert "3 DDIM steps" in ddim_summary


def test_real_edit_with_the_student_runs_no_inversion(client, walk_bvh):
    video, summary, files = edit_real(client, handle_file(str(walk_bvh)), inversion="null_text", seed=5)
    assert Path(video).stat().st_size > 0 and joints_of(files).shape == (32, 22, 3)
    assert "no inversion, 2 consistency steps (distilled student), seed 5, CFG 5" in summary
    assert "Edited in" in summary and "Inverted" not in summary and "null" not in summary.lower()
    assert "Reconstruction error (MPJPE)" in summary
    # the inversion choice does not apply: the same edit with another one is the same request
    _, again, _ = edit_real(client, handle_file(str(walk_bvh)), inversion="ddim", seed=5)
    assert again == summary, "answered from the first edit (same timings)"
    _, teacher, _ = edit_real(client, handle_file(str(walk_bvh)), sampler="ddim", steps=2)
    assert "negative prompt inversion, 2 DDIM steps" in teacher and "Inverted in" in teacher


def test_the_studio_offers_the_student_and_its_steps(server, client):
    p = props(server[1].demo)
    assert [c[1] for c in p["sampler"]["choices"]] == ["consistency", "dpm-sde", "ddim", "dpm"]
    assert p["sampler"]["choices"][0][0] == "fast: distilled student, 4 steps"
    assert p["sampler"]["choices"][1][0] == "standard: SDE-DPM-Solver++, 25 steps"
    assert p["sampler"]["choices"][2][0] == "quality: DDIM, 50 steps"
    assert [c[1] for c in p["edit-sampler"]["choices"]] == ["consistency", "dpm-sde", "ddim", "dpm"]
    for elem in ("control-sampler", "real-sampler"):
        assert p[elem]["visible"] is not False and [c[1] for c in p[elem]["choices"]] == ["ddim", "consistency"]
    # the default (auto) starts generating on the teacher (dpm-sde) and guided control on the student, as the
    # model has one
    assert p["sampler"]["value"] == "dpm-sde" and p["steps"]["value"] == 25
    assert p["control-sampler"]["value"] == "consistency" and p["control-steps"]["value"] == 4
    # picking a sampler sets its default steps (and the student's range)
    for api in ("/sampler_steps", "/edit_sampler_steps", "/control_sampler_steps"):
        fast = client.predict("consistency", api_name=api)
        assert fast["value"] == DEFAULT_STEPS["consistency"] == 4 and fast["maximum"] == 50, api
        slow = client.predict("ddim", api_name=api)
        assert slow["value"] == 50 and slow["maximum"] == 200, api
    steps, inversion, seed = client.predict("consistency", api_name="/real_sampler")
    assert steps["value"] == 4 and "no inversion" in steps["info"]
    assert inversion["interactive"] is False and seed["visible"] is True
    steps, inversion, seed = client.predict("ddim", api_name="/real_sampler")
    assert steps["value"] == 50 and inversion["interactive"] is True and seed["visible"] is False


def test_the_student_refuses_what_it_cannot_do(client):
    with pytest.raises(AppError, match="steps must be an integer in 1..50 for the consistency sampler"):
        generate(client, steps=60)
    with pytest.raises(AppError, match=r"distilled for cfg 2..8"):
        generate(client, cfg=12.0)
    with pytest.raises(AppError, match="guided control samples with ddim or consistency"):
        control(client, sampler="dpm")
    with pytest.raises(AppError, match="a real-motion edit samples with ddim or consistency"):
        edit_real(client, None, sampler="dpm")


def test_the_default_sampler_of_each_panel(student_pipe, pipe, tmp_path, caplog, monkeypatch):
    ws = Workspace(tmp_path)
    try:
        p = props(build_studio(Studio(student_pipe, ws, sampler="consistency"), Settings(tmp_dir=tmp_path)))
        for radio, steps in (("sampler", "steps"), ("edit-sampler", "edit-steps"),
                             ("control-sampler", "control-steps"), ("real-sampler", "real-steps")):
            assert p[radio]["value"] == "consistency" and p[steps]["value"] == 4, radio
            assert p[steps]["maximum"] == 50
        assert p["real-seed"]["visible"] is True and p["real-inversion"]["interactive"] is False
        assert Studio(student_pipe, ws, sampler="consistency").control_sampler == "consistency"
        # the default (auto): the student where its checkpoint records that it was measured fit (here:
        # guided control), else the teacher, quietly, as where there is no student
        monkeypatch.delitem(student_pipe.student_info, "default_for")
        assert (Studio(student_pipe, ws).default_sampler, Studio(student_pipe, ws).control_sampler) == ("dpm-sde",
                                                                                                        "ddim")
        # (Generate, Edit, Control) samplers, then the Generate, Edit and Real motion radios
        for uses, samplers, radios in ((["text", "control"], ("consistency", "dpm-sde", "consistency"),
                                        ("consistency", "dpm-sde", "ddim")),
                                       (["edit"], ("dpm-sde", "consistency", "ddim"),
                                        ("dpm-sde", "consistency", "consistency"))):
            monkeypatch.setitem(student_pipe.student_info, "default_for", uses)
            studio = Studio(student_pipe, ws)
            assert (studio.default_sampler, studio.edit_sampler, studio.control_sampler) == samplers, uses
            p = props(build_studio(studio, Settings(tmp_dir=tmp_path)))
            assert tuple(p[r]["value"] for r in ("sampler", "edit-sampler", "real-sampler")) == radios, uses
        monkeypatch.setitem(student_pipe.student_info, "default_for", ["control"])
        auto = Studio(student_pipe, ws)
        assert (auto.default_sampler, auto.edit_sampler, auto.control_sampler) == ("dpm-sde", "dpm-sde",
                                                                                   "consistency")
        p = props(build_studio(auto, Settings(tmp_dir=tmp_path)))
        for radio, steps, sampler, n in (("sampler", "steps", "dpm-sde", 25),
                                         ("edit-sampler", "edit-steps", "dpm-sde", 25),
                                         ("control-sampler", "control-steps", "consistency", 4),
                                         ("real-sampler", "real-steps", "ddim", 50)):
            assert p[radio]["value"] == sampler and p[steps]["value"] == n, radio
        with caplog.at_level(logging.WARNING, logger="salad.studio"):
            plain = Studio(pipe, ws)
        assert (plain.default_sampler, plain.control_sampler) == ("dpm-sde", "ddim")
        assert "no consistency student" not in caplog.text
        # asking for the student of a model without one falls back to the teacher, with a warning
        with caplog.at_level(logging.WARNING, logger="salad.studio"):
            studio = Studio(pipe, ws, sampler="consistency")
        assert (studio.default_sampler, studio.edit_sampler, studio.control_sampler) == ("dpm-sde", "dpm-sde",
                                                                                         "ddim")
        assert "no consistency student" in caplog.text
        p = props(build_studio(studio, Settings(tmp_dir=tmp_path)))
        assert p["sampler"]["value"] == "dpm-sde" and p["steps"]["value"] == 25
        assert p["control-steps"]["value"] == 50 and p["real-steps"]["value"] == 50
        # the quality choice: every panel on DDIM-50
        p = props(build_studio(Studio(pipe, ws, sampler="ddim"), Settings(tmp_dir=tmp_path)))
        assert (p["sampler"]["value"], p["steps"]["value"], p["edit-steps"]["value"]) == ("ddim", 50, 50)
    finally:
        ws.close()


def test_the_sampler_setting(tmp_path):
    from app.cli import parse_args

    assert Settings().sampler == "auto" and parse_args([]).sampler == "auto"
    assert parse_args(["--sampler", "consistency"]).sampler == "consistency"
    with pytest.raises(ValueError, match="sampler must be one of auto, dpm-sde, ddim, dpm, consistency"):
        Settings(sampler="euler")
    with pytest.raises(SystemExit):
        parse_args(["--sampler", "euler"])


def test_the_precision_setting():
    from app.cli import parse_args

    assert Settings().precision == "auto" and parse_args([]).precision == "auto"
    assert Settings().bf16_rows == (True, 2)            # bf16 from two rows a forward, where the CPU has it
    assert Settings(precision="fp32").bf16_rows[0] is False and Settings(precision="bf16").bf16_rows == (True, 1)
    assert parse_args(["--precision", "fp32"]).precision == "fp32"
    with pytest.raises(ValueError, match="precision must be one of auto, fp32, bf16"):
        Settings(precision="half")
    with pytest.raises(SystemExit):
        parse_args(["--precision", "half"])


def test_validation_carries_the_sampler(student_pipe, walk_bvh, tmp_path):
    req, _ = parse_control(student_pipe, "a person walks", "path", "circle", 1.2, 1.0, None, "", "", 1.0, 0, 3, CFG,
                           True, "consistency")
    assert (req.sampler, req.steps) == ("consistency", 3)
    req, _ = parse_control(student_pipe, "a person walks", "path", "circle", 1.2, 1.0, None, "", "", 1.0, 0, 3, CFG)
    assert req.sampler == "ddim", "a caller without the sampler gets DDIM"
    upload = tmp_path / "walk.bvh"
    upload.write_bytes(walk_bvh.read_bytes())
    args = (student_pipe, str(upload), "", "a person walks forward", "mirror", "", "", 2.0, "all")
    fast, _ = parse_real_edit(*args, "fixed_point", 4, CFG, True, "consistency", 7, upload_root=tmp_path)
    assert (fast.sampler, fast.inversion, fast.seed) == ("consistency", None, 7)
    slow, _ = parse_real_edit(*args, "fixed_point", 4, CFG, True, "ddim", 7, upload_root=tmp_path)
    assert (slow.sampler, slow.inversion, slow.seed) == ("ddim", "fixed_point", 0), "the inversion needs no seed"


# ---------------------------------------------------------------- without a student

def test_without_a_student_consistency_is_neither_offered_nor_accepted(plain_server, plain_client, walk_bvh):
    p = props(plain_server[1].demo)
    assert [c[1] for c in p["sampler"]["choices"]] == ["dpm-sde", "ddim", "dpm"]
    assert [c[1] for c in p["edit-sampler"]["choices"]] == ["dpm-sde", "ddim", "dpm"]
    assert p["control-sampler"]["visible"] is False and p["real-sampler"]["visible"] is False
    assert p["control-steps"]["label"] == "Diffusion steps (DDIM)"
    for call in (lambda: generate(plain_client), lambda: edit(plain_client), lambda: control(plain_client),
                 lambda: edit_real(plain_client, handle_file(str(walk_bvh)))):
        with pytest.raises(AppError, match=NO_STUDENT):
            call()
    # the teacher still serves, and control and real edits default to it
    _, summary, _ = plain_client.predict(handle_file(str(walk_bvh)), "", "a person walks forward", "mirror", "", "",
                                         2.0, "all", "negative", 2, CFG, api_name="/edit_real")
    assert "2 DDIM steps" in summary and "Inverted in" in summary
