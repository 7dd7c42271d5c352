"""Entry point for `python -m app` and for `python app/__main__.py` (Hugging Face Spaces runs the file)."""
import sys
from pathlib import Path

if not __package__:
    # Run as a file: import the package from the repository root instead of this folder.
    here = Path(__file__).resolve().parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != here]
    sys.path.insert(0, str(here.parent))

from app.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
