"""Memory as the project's parts see it: the machine's RAM, a process's own peak, and process-wide tuning of
glibc's allocator (mallopt): large allocations for training loops, a filled heap for reproducible encodes.
Elsewhere than glibc both tunings are no-ops that say so."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
from collections.abc import Callable


def physical_memory() -> int | None:
    """Bytes of RAM of this machine, or None where the OS does not say."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def process_peak_rss_mb() -> float | None:
    """This process's peak resident memory so far (MB), where the OS reports it.

    On Linux this is /proc/self/status's VmHWM, the high-water mark of this program's own memory: getrusage's
    ru_maxrss survives exec, so a program started by a large process (a benchmark that packed a scene first)
    would report its parent's peak instead of its own."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource
    except ImportError:
        return None
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kilobytes on Linux


M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
M_PERTURB = -6


def _mallopt() -> Callable[[int, int], int] | None:
    """glibc's mallopt, or None where the C library has none."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):
        return None
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return mallopt


def reuse_large_allocations() -> bool:
    """Serve large allocations from glibc's heap instead of fresh mmaps, and keep freed memory.

    A training step allocates and frees gradient buffers of the whole feature tensor (tens of MB);
    fresh mmaps page-fault on first touch, which makes zero-filling them several times slower. Returns False
    (and changes nothing) where the C library is not glibc.
    """
    mallopt = _mallopt()
    if mallopt is None:
        return False
    settings = ((M_MMAP_THRESHOLD, 1 << 30), (M_TRIM_THRESHOLD, 2 ** 31 - 1), (M_TOP_PAD, 256 << 20))
    return all(mallopt(param, value) == 1 for param, value in settings)


class FilledHeap:
    """A context in which glibc's malloc fills the blocks it hands out with one fixed byte (M_PERTURB; blocks
    from the per-thread cache, at most 1 KiB, are not filled).

    For native code that reads memory it never wrote (the libx265 in PyAV's wheel: valgrind shows thousands of
    such reads per encode): its output then depends on its inputs alone, not on what the process's heap held
    before. The setting is process-wide and costs a memset per allocation, so it is on only while at least one
    context is open (contexts may overlap across threads). `available` is False where there is no mallopt:
    the context then changes nothing."""

    FILL = 0xA5

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open = 0
        self._mallopt = _mallopt()

    @property
    def available(self) -> bool:
        return self._mallopt is not None

    def _set(self, value: int) -> None:
        if self._mallopt is not None:
            self._mallopt(M_PERTURB, value)

    def __enter__(self) -> FilledHeap:
        with self._lock:
            if self._open == 0:
                self._set(self.FILL)
            self._open += 1
        return self

    def __exit__(self, *exc) -> None:
        with self._lock:
            self._open -= 1
            if self._open == 0:
                self._set(0)


filled_heap = FilledHeap()
"""The process's one FilledHeap (its on/off count must be shared by every user)."""
