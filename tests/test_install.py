import subprocess
import sys
from pathlib import Path


def test_the_package_imports_from_anywhere(tmp_path):
    # a stale editable install can leave `salad` a namespace package outside the repository
    out = subprocess.run([sys.executable, "-c", "import salad; print(salad.__file__); salad.load_pipeline"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()) == Path(__file__).resolve().parent.parent / "salad" / "__init__.py"
