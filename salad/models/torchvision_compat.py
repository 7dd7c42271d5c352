"""Importing torchvision (which transformers and open_clip pull in) where its compiled ops do not load.

torchvision wheels whose compiled ops do not load (e.g. a CUDA build next to a CPU torch) die at import
time when registering fake kernels for ops whose schemas were never defined. Defining just those schemas
lets the pure-Python parts import; the compiled ops themselves remain unavailable.
"""
from __future__ import annotations

import re
import sys
import threading

import torch

_TORCHVISION_OP_SCHEMAS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}
_MISSING_OP_RE = re.compile(r"operator torchvision::(\w+) does not exist")
_torchvision_schema_lib: "torch.library.Library | None" = None  # kept alive: dropping it undefines the ops
_torchvision_defined_ops: list[str] = []
_import_lock = threading.Lock()


def defined_torchvision_ops() -> list[str]:
    """The torchvision op schemas this process had to define to import torchvision."""
    return list(_torchvision_defined_ops)


def _define_torchvision_op(op: str) -> None:
    global _torchvision_schema_lib
    if _torchvision_schema_lib is None:
        _torchvision_schema_lib = torch.library.Library("torchvision", "FRAGMENT")
    _torchvision_schema_lib.define(_TORCHVISION_OP_SCHEMAS[op])
    _torchvision_defined_ops.append(op)


def ensure_torchvision_importable() -> list[str]:
    """Import torchvision, working around missing compiled-op schemas only when that failure occurs.

    Returns the op names defined by this call (empty when torchvision imported as is, or is not installed).
    Other import errors propagate unchanged.
    """
    added: list[str] = []
    with _import_lock:
        for _ in range(len(_TORCHVISION_OP_SCHEMAS) + 1):
            try:
                import torchvision  # noqa: F401
                return added
            except ImportError:
                return added  # not installed: callers that need it report it themselves
            except RuntimeError as err:
                match = _MISSING_OP_RE.search(str(err))
                if match is None:
                    raise
                op = match.group(1)
                if op not in _TORCHVISION_OP_SCHEMAS or op in _torchvision_defined_ops:
                    raise RuntimeError(
                        f"torchvision cannot be imported: its compiled ops did not load and the missing op "
                        f"'torchvision::{op}' has no known schema to define ({err})") from err
                # the failed import left half-initialised torchvision modules behind
                for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
                    del sys.modules[name]
                _define_torchvision_op(op)
                added.append(op)
    raise RuntimeError("torchvision still fails to import after defining the missing op schemas")


def import_open_clip():
    """Import ``open_clip`` (slow; done only when an OpenCLIP encoder is requested)."""
    ensure_torchvision_importable()
    import open_clip
    return open_clip
