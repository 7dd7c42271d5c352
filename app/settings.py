"""Run-time settings of the studio and the limits its inputs are checked against."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

# the panels read the edit's defaults and limits here
from salad.editing.spec import DEFAULT_SELF_INJECT, DEFAULT_TAU, MAX_REWEIGHT, MIRROR_PARTS  # noqa: F401
from salad.precision import BF16_MIN_ROWS

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7860

# Input limits. The pipeline accepts wider ranges; the studio keeps requests within what a
# 2-core CPU answers in reasonable time.
MAX_STEPS = 200
DEFAULT_STEPS = 50          # the teacher's (ddim, dpm); salad.pipeline.DEFAULT_STEPS has every sampler's
# auto: the distilled student where its checkpoint records it measured fit (the embedded one: motions from text and
# guided control), else the teacher: dpm-sde's steps for text and edits, DDIM for control and real-motion edits
# (app.studio.Studio says why)
DEFAULT_SAMPLER = "auto"
STUDIO_SAMPLERS = ("auto", "dpm-sde", "ddim", "dpm", "consistency")
MAX_CFG = 15.0
DEFAULT_CFG = 7.5
MAX_SEED = 2**31 - 1
DEFAULT_SECONDS = 4.0
SECONDS_STEP = 0.2          # frames come in multiples of 4 at 20 fps

# Editing (SALAD's attention modulation); its defaults and limits are salad.editing.spec's.
DEFAULT_REWEIGHT = 2.0

# Guided control (MoLA's training-free guidance).
MAX_STRENGTH = 20.0
DEFAULT_STRENGTH = 1.0      # Pipeline.control's default (its guidance steps search their own size)
DEFAULT_PATH_SPEED = 1.0    # m/s along a preset path: an ordinary walk
MAX_PATH_SPEED = 3.0
MAX_UPLOAD_BYTES = 4_000_000   # the largest Bandai BVH clip is 2.4 MB; a (196, 22, 3) float64 target ~100 kB

# Editing real motions (BVH / NPY uploads, or test clips of a dataset build).
REAL_UPLOAD_TYPES = (".bvh", ".npy")   # a Bandai BVH clip is 30 kB to 300 kB (90% of them), 2.4 MB at most
MAX_CLIPS = 120                         # test clips offered in the picker, spread over the split
DEFAULT_CLIPS = Path(__file__).resolve().parents[1] / "data" / "bandai-hml"
CLIP_LAYOUT = ("new_joint_vecs", "texts", "test.txt")   # what a dataset build must hold to offer clips


# How the model thread computes: "auto" is the library's own rule (salad.precision.BF16_MIN_ROWS: bf16
# autocast for forwards of two rows or more on a CPU with native bf16, fp32 otherwise); "fp32" and "bf16"
# run every forward so. Measured on an AVX-512 BF16 EPYC whose bf16 matmuls ran 2.3x its fp32 ones
# (session 52, in the studio, medians of 9 generations and 3 fresh edits per setting, interleaved):
# sampling a generation 1.18 s fp32, 1.21 bf16, 1.10 auto; an edit's 1.91, 1.69, 1.56 (one row a forward:
# see BF16_MIN_ROWS). CPUs without native bf16 run fp32 whatever is asked.
PRECISIONS = ("auto", "fp32", "bf16")
MAX_RENDER_WORKERS = 7     # salad.render.workers.MAX_WORKERS


@dataclass(frozen=True)
class Settings:
    """How the studio is started. `model=None` means $SALAD_MODEL or the embedded model."""

    model: str | None = None
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    concurrency: int = 2            # simultaneous jobs; sampling itself is serialised
    queue_size: int = 32            # waiting jobs beyond this are refused
    session_ttl_s: float = 2 * 3600  # idle sessions and their files are removed after this
    prune_every_s: float = 600
    tmp_dir: Path | None = None     # parent of the studio's private temp root
    threads: int | None = None      # torch threads of the model thread (app.model_thread); None: torch's default
    precision: str = "auto"         # PRECISIONS
    control_examples: Path | None = None   # a folder of MoLA-style control .npy files offered in the Control tab
    clips: Path | None = None       # a dataset build (HumanML3D layout) whose test clips the Real motion tab offers
    sampler: str = DEFAULT_SAMPLER  # the panels' default sampler (ddim when the model has no student)
    render_workers: int = 1         # processes that draw a share of each video's frames (salad.render.workers)

    def __post_init__(self):
        if not 1 <= self.port <= 65535:
            raise ValueError(f"port must be in 1..65535, got {self.port}")
        if not 1 <= self.concurrency <= 8:
            raise ValueError(f"concurrency must be in 1..8, got {self.concurrency}")
        if self.queue_size < 1:
            raise ValueError(f"queue size must be positive, got {self.queue_size}")
        if self.session_ttl_s <= 0 or self.prune_every_s <= 0:
            raise ValueError("session ttl and prune interval must be positive")
        if self.sampler not in STUDIO_SAMPLERS:
            raise ValueError(f"sampler must be one of {', '.join(STUDIO_SAMPLERS)}, got {self.sampler!r}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be positive, got {self.threads}")
        if not 0 <= self.render_workers <= MAX_RENDER_WORKERS:
            raise ValueError(f"render workers must be in 0..{MAX_RENDER_WORKERS}, got {self.render_workers}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if self.control_examples is not None and not Path(self.control_examples).is_dir():
            raise ValueError(f"{self.control_examples}: the control examples folder does not exist")
        if self.clips is not None:
            missing = [name for name in CLIP_LAYOUT if not (Path(self.clips) / name).exists()]
            if missing:
                raise ValueError(f"{self.clips}: not a dataset build (it lacks {', '.join(missing)}); "
                                 "make one with `salad data build`")

    @property
    def bf16_rows(self) -> tuple[bool, int]:
        """(bf16, bf16_min_rows) for load_pipeline."""
        return (self.precision != "fp32", BF16_MIN_ROWS if self.precision == "auto" else 1)


def default_host() -> str:
    """127.0.0.1, unless GRADIO_SERVER_NAME says otherwise (Hugging Face Spaces sets it to 0.0.0.0)."""
    return os.environ.get("GRADIO_SERVER_NAME") or DEFAULT_HOST


def default_clips() -> Path | None:
    """The repository's own dataset build (data/bandai-hml), when it has been built."""
    return DEFAULT_CLIPS if all((DEFAULT_CLIPS / name).exists() for name in CLIP_LAYOUT) else None


def default_port() -> int:
    value = os.environ.get("GRADIO_SERVER_PORT")
    return int(value) if value and value.isdigit() else DEFAULT_PORT
