"""The notebooks: committed without outputs, and each one runs headless from top to bottom.

Execution injects small settings after each notebook's "parameters" cell (papermill's convention) and runs
a copy on a kernel started from this interpreter (the project venv), with the working directory notebooks/
as a user has it and outputs in a temporary folder. Two notebooks run at a time, one thread each. The
executed copies go to test-artifacts/notebooks/ for inspection.
"""
import asyncio
import base64
import json
import os
import re
import sys
import time
from pathlib import Path

import nbformat
import pytest
from jupyter_client.kernelspec import KernelSpecManager
from jupyter_client.manager import AsyncKernelManager
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

from conftest import shared_data_dir

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = REPO / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
ARTIFACTS = REPO / "test-artifacts" / "notebooks"
SMALL = {"STEPS": 6, "FAST": True, "THREADS": 1}
CELL_TIMEOUT_S = 300
PARALLEL = max(1, min(2, int(os.environ.get("SALAD_NOTEBOOK_JOBS", "2"))))
NEEDS_SHARED_DATA = {"05_train_on_your_mocap"}

# What each notebook must show when it ran: embedded MP4 videos, Plotly figures and static images (at
# least), and files it must have written into OUT_DIR.
EXPECT = {
    "01_generate_and_render": dict(videos=3, plotly=1, images=2,
                                   files=["motion.mp4", "motion.bvh", "motion.npz", "variations.mp4"]),
    "02_attention_maps": dict(videos=1, plotly=5, images=2,
                              files=["attention.png", "attention_maps.npz", "words_by_parts.csv"]),
    "03_prompt_to_prompt_editing": dict(videos=4, plotly=0, images=2,
                                        files=["refine.mp4", "reweight.mp4", "mirror_upper.mp4", "swap.mp4"]),
    "04_guided_control": dict(videos=3, plotly=0, images=3, files=["path.mp4", "inbetween.mp4", "upper_body.mp4"]),
    "05_train_on_your_mocap": dict(videos=2, plotly=0, images=2,
                                   files=["model/denoiser/config.json", "model/vae/config.json", "evaluation.csv"]),
}


def test_every_notebook_is_known():
    assert NOTEBOOKS, f"no notebooks in {NOTEBOOK_DIR}"
    assert sorted(p.stem for p in NOTEBOOKS) == sorted(EXPECT)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_notebook_is_clean(path):
    """No outputs or execution counts in git, an intro first, one parameters cell that CI can override."""
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    dirty = [i for i, c in enumerate(nb.cells) if c.cell_type == "code"
             and (c.outputs or c.execution_count is not None or "execution" in c.metadata)]
    assert not dirty, f"{path.name}: cells {dirty} carry outputs; clear them before committing"
    assert nb.cells[0].cell_type == "markdown" and nb.cells[0].source.startswith("# "), \
        f"{path.name}: the first cell should be a markdown introduction with a title"
    params = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(params) == 1, f"{path.name}: expected one cell tagged 'parameters', found {len(params)}"
    for name in list(SMALL) + ["OUT_DIR"]:
        assert re.search(rf"^{name}\s*=", params[0].source, re.M), f"{path.name}: parameters cell lacks {name}"
    assert nb.metadata.get("kernelspec", {}).get("language") == "python"


# ---------------------------------------------------------------- execution

def _kernel_manager(spec_dir: Path) -> AsyncKernelManager:
    """A kernel on this very interpreter, single-threaded and offline, whatever Jupyter finds elsewhere."""
    kdir = spec_dir / "salad-test"
    kdir.mkdir(parents=True, exist_ok=True)
    env = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PLOTLY_RENDERER": "plotly_mimetype",
           "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "PYDEVD_DISABLE_FILE_VALIDATION": "1"}
    (kdir / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-Xfrozen_modules=off", "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "salad test kernel", "language": "python", "env": env}))
    specs = KernelSpecManager(kernel_dirs=[str(spec_dir)])
    return AsyncKernelManager(kernel_name="salad-test", kernel_spec_manager=specs)


def _with_parameters(path: Path, out_dir: Path) -> nbformat.NotebookNode:
    nb = nbformat.read(path, as_version=4)
    i = next(k for k, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", []))
    values = dict(SMALL, OUT_DIR=str(out_dir))
    source = "\n".join(f"{k} = {v!r}" for k, v in values.items())
    source += f"\nimport sys as _sys\nassert _sys.executable == {sys.executable!r}, _sys.executable"
    nb.cells.insert(i + 1, nbformat.v4.new_code_cell(source, metadata={"tags": ["injected-parameters"]}))
    return nb


async def _run_all(paths: list[Path], work: Path) -> dict[str, dict]:
    gate = asyncio.Semaphore(PARALLEL)
    results: dict[str, dict] = {}

    async def run(path: Path) -> None:
        async with gate:
            out = work / path.stem
            out.mkdir(parents=True, exist_ok=True)
            nb = _with_parameters(path, out)
            client = NotebookClient(nb, km=_kernel_manager(work / "kernels" / path.stem), timeout=CELL_TIMEOUT_S,
                                    resources={"metadata": {"path": str(NOTEBOOK_DIR)}})
            start = time.perf_counter()
            error = None
            try:
                await client.async_execute()
            except CellExecutionError as e:
                error = str(e)
            except Exception as e:             # a dead kernel or a timeout: report it against this notebook
                error = f"{type(e).__name__}: {e}"
            results[path.stem] = {"nb": nb, "seconds": time.perf_counter() - start, "error": error, "out": out}

    await asyncio.gather(*(run(p) for p in paths))
    return results


@pytest.fixture(scope="module")
def executed(tmp_path_factory) -> dict[str, dict]:
    """Every notebook, executed once with small settings (those needing absent data are left out)."""
    have_data = shared_data_dir() is not None
    paths = [p for p in NOTEBOOKS if have_data or p.stem not in NEEDS_SHARED_DATA]
    work = tmp_path_factory.mktemp("notebooks")
    start = time.perf_counter()
    results = asyncio.run(_run_all(paths, work))
    total = time.perf_counter() - start
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for name, r in results.items():
        nbformat.write(r["nb"], str(ARTIFACTS / f"{name}.ipynb"))
    timings = {name: round(r["seconds"], 1) for name, r in sorted(results.items())}
    (ARTIFACTS / "timings.json").write_text(json.dumps({"parallel": PARALLEL, "wall_s": round(total, 1),
                                                        "per_notebook_s": timings}, indent=2) + "\n")
    return results


def _outputs(nb) -> list[dict]:
    return [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]


def _videos(outputs) -> list[bytes]:
    found = []
    for o in outputs:
        html = o.get("data", {}).get("text/html", "")
        found += [base64.b64decode(m) for m in re.findall(r'src="data:video/mp4;base64,([A-Za-z0-9+/=\s]+)"', html)]
    return found


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EXPECT))
def test_notebook_runs_and_shows_its_results(name, executed):
    if name not in executed:
        assert name in NEEDS_SHARED_DATA
        pytest.skip(f"{name} needs the shared data (set SALAD_SHARED_DATA)")
    r = executed[name]
    assert r["error"] is None, f"{name} failed after {r['seconds']:.0f} s:\n{r['error'][-4000:]}"
    outputs = _outputs(r["nb"])
    errors = [o for o in outputs if o.get("output_type") == "error"]
    assert not errors, f"{name}: error outputs {[e.get('ename') for e in errors]}"
    want = EXPECT[name]

    videos = _videos(outputs)
    assert len(videos) >= want["videos"], f"{name}: {len(videos)} embedded videos, expected {want['videos']}"
    for v in videos:
        assert len(v) > 2000 and v[4:8] == b"ftyp", f"{name}: an embedded video is not an MP4"
    figures = [o for o in outputs if "application/vnd.plotly.v1+json" in o.get("data", {})]
    assert len(figures) >= want["plotly"], f"{name}: {len(figures)} Plotly figures, expected {want['plotly']}"
    for f in figures:
        assert f["data"]["application/vnd.plotly.v1+json"].get("data"), f"{name}: an empty Plotly figure"
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= want["images"], f"{name}: {len(images)} images, expected {want['images']}"
    for rel in want["files"]:
        f = r["out"] / rel
        assert f.is_file() and f.stat().st_size > 0, f"{name}: did not write {rel} into OUT_DIR"
    assert r["seconds"] < 240, f"{name} took {r['seconds']:.0f} s with the small settings"
