"""The C allocator's handling of large blocks, for inference on the CPU.

glibc serves every block above its mmap threshold (128 KiB to start with) from a fresh
mapping and unmaps it on free, so each decode's activations (a 96-channel decoder on 22 joints
x 120 frames is about 1 MB a tensor) come back as pages the kernel must fault in and zero
again. On this project's 2-core machines that was about a tenth of a 4-step generation
(median 67-69 ms against 58-61 ms with large blocks kept in the heap, two processes each way). Raising the threshold keeps
freed blocks for reuse; the memory stays the process's until it exits, bounded by the
largest working set it had.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt's parameter numbers (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
KEEP_BELOW_BYTES = 256 << 20     # blocks up to this size stay in the heap after free

_kept = False


def keep_large_blocks() -> bool:
    """Keep freed blocks up to KEEP_BELOW_BYTES in the heap (glibc only, once per process).
    Returns whether the allocator now does; False where the C library has no mallopt."""
    global _kept
    if _kept or not sys.platform.startswith("linux"):
        return _kept
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):   # musl and other C libraries without mallopt
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _kept = bool(mallopt(_M_MMAP_THRESHOLD, KEEP_BELOW_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, KEEP_BELOW_BYTES))
    return _kept
