"""What a playback needs of the machine: enough memory for its decoded GOPs, a garbage collector that does
not pause it, and its peak memory for the log."""

from __future__ import annotations

import contextlib
import gc
import os
from collections.abc import Iterator

from stgs.client.config import PlaybackError


def physical_memory() -> int | None:
    """Bytes of RAM of this machine, or None where the OS does not say."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Playback with every object alive at its start (torch, the libraries, the scene's setup) moved out of
    the garbage collector's reach: a full collection traversed them all in the middle of playback, once a
    minute, and its 130 ms dropped four frames (docs/BENCHMARKS.md, "Real-time playback")."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def process_peak_rss_mb() -> float | None:
    """The player process's peak resident memory so far (MB), where the OS reports it."""
    try:
        import resource
    except ImportError:
        return None
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kilobytes on Linux
    return kb / 1024


def check_decode_memory(gop_bytes: int, max_decoded: int, ram: int | None = None) -> None:
    """Refuse, before fetching anything, a presentation whose decoded GOPs (`max_decoded` of them at once) need
    more memory than the machine has."""
    ram = physical_memory() if ram is None else ram
    need = gop_bytes * max_decoded
    if ram is not None and need > ram:
        raise PlaybackError(f"decoding needs {need / 2**30:.1f} GiB ({max_decoded} GOPs of "
                            f"{gop_bytes / 2**30:.1f} GiB at once); this machine has {ram / 2**30:.1f} GiB")
