"""Evaluation: the T2M protocol, the editing, control and length benchmarks, and the networks they use."""
from pathlib import Path

# Trained on the embedded model's data build and shipped with it, so every benchmark runs from a fresh clone.
EMBEDDED_EVALUATOR = Path(__file__).resolve().parent.parent.parent / "assets" / "eval" / "evaluator"
EMBEDDED_CLASSIFIER = EMBEDDED_EVALUATOR.parent / "classifier"
