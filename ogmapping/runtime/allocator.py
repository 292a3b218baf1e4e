"""Keep freed memory in the process (glibc): CPU mapping allocates and frees megabyte images all the time.

glibc's malloc serves large blocks with fresh ``mmap`` pages and hands freed heap memory back to
the system, so every render, loss image and gradient buffer page-faults its memory in again. A
mapping iteration allocates tens of such buffers; keeping them in the heap made the fused loss
1.6x and sparse mapping 1.07x faster (bench/RESULTS.md). The thresholds bound what is kept.
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # blocks at least this large still get their own mapping
TRIM_THRESHOLD_BYTES = 128 * 1024 * 1024  # free memory kept at the top of the heap before returning it


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds; False where the C library is not glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
