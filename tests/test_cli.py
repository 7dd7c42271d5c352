"""The `salad` command's start-up: its parser is built without torch, so `--help` and argument errors answer at
once; the values it spells out to stay free of torch agree with the library's; it and the studio start offline."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from salad.cli import build_parser
from salad.environment import OFFLINE_DEFAULTS

HEAVY = ("torch", "numpy", "scipy", "diffusers")


def test_parser_and_help_load_no_heavy_module():
    code = ("import sys, contextlib, io\n"
            "import salad.cli\n"
            "for argv in (['--help'], ['control', '--help'], ['eval-fidelity', '--help'], ['edit', 'x', '--mode', 'bad']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
            "        try:\n"
            "            salad.cli.main(argv)\n"
            "        except SystemExit as e:\n"
            "            assert e.code in (0, 2), (argv, e.code)\n"
            f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def _defaults(command: str) -> dict:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return {a.dest: a for a in sub.choices[command]._actions}


def test_spelled_out_values_agree_with_the_library():
    from salad.editing.real import DEFAULT_INVERSION
    from salad.eval.control_bench import OMNICONTROL_JOINTS
    from salad.eval.length_dist import DEFAULT_BIN_FRAMES
    from salad.eval.real_edit_bench import SDEDIT_STRENGTHS
    from salad.motion.control import PATH_PRESETS

    assert tuple(_defaults("control")["path_preset"].choices) == PATH_PRESETS
    inversion = _defaults("edit-real")["inversion"]
    assert inversion.default == DEFAULT_INVERSION and f"{DEFAULT_INVERSION} (default)" in inversion.help
    assert _defaults("eval-length")["bin_frames"].default == DEFAULT_BIN_FRAMES
    assert [float(s) for s in _defaults("eval-real-edit")["sdedit"].default.split(",")] == list(SDEDIT_STRENGTHS)
    assert ",".join(OMNICONTROL_JOINTS) in _defaults("eval-control")["joints"].help


def test_an_output_that_cannot_be_written_fails_before_the_model_loads(tmp_path, capsys):
    from salad.cli import main

    afile = tmp_path / "a.txt"
    afile.write_text("x")
    missing_model = str(tmp_path / "no-model")
    for argv in (["generate", "walk", "-o", str(afile / "walk.npy")], ["edit", "walk", "run", "-o", str(afile / "out")],
                 ["control", "walk", "--path-preset", "line", "-o", str(afile / "walk.bvh")]):
        assert main(argv + ["--model", missing_model]) == 2
        err = capsys.readouterr().err
        assert "is not a directory" in err and "no-model" not in err, err


def test_the_console_command_keeps_main_s_exit_status():
    salad = Path(sys.executable).with_name("salad")
    assert salad.is_file(), "the package is installed with its `salad` console command (make setup)"
    ok = subprocess.run([str(salad), "--help"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "generate" in ok.stdout
    bad = subprocess.run([str(salad), "generate", "walk", "-o", "walk.txt"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "unsupported output type" in bad.stderr


@pytest.mark.parametrize("entry", ["import app", "import salad.cli; salad.cli.main(['data', '--help'])"])
def test_the_command_and_the_studio_start_offline_keeping_what_the_caller_set(entry):
    code = ("import contextlib, io, os\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n"
            f"        {entry}\n"
            "    except SystemExit:\n"
            "        pass\n"
            "print(os.environ['HF_HUB_OFFLINE'], os.environ['TRANSFORMERS_OFFLINE'], "
            "os.environ['GRADIO_ANALYTICS_ENABLED'])\n")
    env = {k: v for k, v in os.environ.items() if k not in OFFLINE_DEFAULTS}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "1", "False"]
    env["TRANSFORMERS_OFFLINE"] = "0"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.stdout.split() == ["1", "0", "False"]
    plain = subprocess.run([sys.executable, "-c", "import os, salad; print('HF_HUB_OFFLINE' in os.environ)"],
                           capture_output=True, text=True, timeout=120, env=env)
    assert plain.stdout.strip() == "False"      # the library alone leaves the process as it was
