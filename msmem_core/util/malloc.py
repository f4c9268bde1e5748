"""Keep large freed blocks in the heap (glibc), so per-decision temporaries are not page-faulted anew.

glibc serves allocations above its mmap threshold (128 KiB, raised up to 32 MiB as blocks are freed)
with fresh ``mmap`` pages that the kernel zero-fills on first touch, and trims the heap top above its
trim threshold. A decision allocates and frees tens of MB of tensors each time (the batched CNABU
prediction: logits, gathered rows, U-Net maps), so every decision paid those page faults again:
about a tenth of a batched prediction's time (docs/explanation/performance.md). Raising both thresholds keeps
the blocks for reuse; the process's resident size stays at its high-water mark instead.

Called by the CLI's ``main`` and by the local executor's workers; a no-op without glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
LIMIT_BYTES = 512 * 1024 * 1024
"""Blocks up to this size come from the heap; the heap top is trimmed only above it."""


def keep_large_allocations(limit_bytes: int = LIMIT_BYTES) -> bool:
    """Raise glibc's mmap and trim thresholds to ``limit_bytes``; False where that is not possible."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, limit_bytes)) and bool(mallopt(_M_TRIM_THRESHOLD, limit_bytes))
