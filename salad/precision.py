"""Where tensors are computed (CPU or a CUDA GPU) and in which precision that device runs fast."""
from __future__ import annotations

import torch

DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"

# bf16 autocast pays off from this many rows a forward: for one row (the student's steps, an unguided
# step) its weight casts cost more than its matmuls save. One row ran 10% slower than fp32 on session 52's
# AVX-512 BF16 EPYC, and the student's four steps 88 against 67 ms on session 69's AMX Xeon; two rows (a
# guided step's pair, an edit's branches) gain.
BF16_MIN_ROWS = 2


def resolve_device(name: str | torch.device | None = "auto") -> torch.device:
    """"auto" is a CUDA GPU when torch sees one, else the CPU. Asking for CUDA where there is
    none is an error rather than a silent fall-back: a run planned for a GPU would otherwise
    crawl on the CPU for hours before anyone noticed."""
    if isinstance(name, torch.device):
        name = str(name)
    name = (name or "auto").strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"unknown device {name!r}: use {DEVICE_CHOICES}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} was asked for, but torch sees no CUDA GPU on this machine; "
                             "use --device cpu (or auto)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA GPU(s)")
    elif device.type != "cpu":
        raise ValueError(f"device {name!r} is not supported: use {DEVICE_CHOICES}")
    return device


def bf16_supported(device: torch.device | str = "cpu") -> bool:
    """Native bf16 matmul: AVX-512 BF16 / AMX on a CPU, Ampere or newer on a GPU. Without it,
    bf16 is emulated at a small fraction of fp32's speed, so bf16 autocast must be skipped,
    not merely tolerated."""
    if torch.device(device).type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def to_device(batch, device: torch.device):
    """A batch (tensors inside dicts, lists and tuples; anything else as it is) on `device`."""
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return {k: to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(to_device(v, device) for v in batch)
    return batch
