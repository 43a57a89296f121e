"""Process-wide tuning of the C allocator for loops that allocate large tensors every iteration."""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3


def reuse_large_allocations() -> bool:
    """Serve large allocations from glibc's heap instead of fresh mmaps, and keep freed memory.

    A training step allocates and frees gradient buffers of the whole feature tensor (tens of MB);
    fresh mmaps page-fault on first touch, which made zero-filling them ~5x slower. Returns False
    (and changes nothing) where the C library is not glibc.
    """
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    settings = ((M_MMAP_THRESHOLD, 1 << 30), (M_TRIM_THRESHOLD, 2 ** 31 - 1), (M_TOP_PAD, 256 << 20))
    return all(mallopt(param, value) == 1 for param, value in settings)
