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
    """The player process's peak resident memory so far (MB), where the OS reports it.

    On Linux this is /proc/self/status's VmHWM, the high-water mark of this program's own memory: getrusage's
    ru_maxrss survives exec, so a player started by a large process (a benchmark that packed a scene first)
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


def check_decode_memory(gop_bytes: int, max_decoded: int, ram: int | None = None, static_bytes: int = 0) -> None:
    """Refuse, before fetching anything, a presentation whose decoded GOPs (`max_decoded` of them at once) and
    static layer (held all along) need more memory than the machine has."""
    ram = physical_memory() if ram is None else ram
    need = gop_bytes * max_decoded + static_bytes
    if ram is not None and need > ram:
        layer = f" and a static layer of {static_bytes / 2**30:.1f} GiB" if static_bytes else ""
        raise PlaybackError(f"decoding needs {need / 2**30:.1f} GiB ({max_decoded} GOPs of "
                            f"{gop_bytes / 2**30:.1f} GiB at once{layer}); this machine has {ram / 2**30:.1f} GiB")
