"""What this CPU can compute fast."""
import torch


def bf16_supported() -> bool:
    """Native bf16 matmul (AVX-512 BF16 / AMX). Without it, oneDNN emulates bf16 at a small
    fraction of fp32's speed, so bf16 autocast must be skipped, not merely tolerated."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False
