"""What a playback needs of the machine: enough memory for its decoded GOPs, a garbage collector that does
not pause it, and its peak memory for the log."""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator

from stgs.client.config import PlaybackError
from stgs.memory import physical_memory, process_peak_rss_mb

__all__ = ["check_decode_memory", "frozen_heap", "physical_memory", "process_peak_rss_mb"]


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Playback with every object alive at its start (torch, the libraries, the scene's setup) moved out of
    the garbage collector's reach: a full collection traversed them all in the middle of playback, once a
    minute, long enough to drop frames (docs/BENCHMARKS.md, "Real-time playback")."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def check_decode_memory(gop_bytes: int, max_decoded: int, ram: int | None = None, static_bytes: int = 0) -> None:
    """Refuse, before fetching anything, a presentation whose decoded GOPs (`max_decoded` of them at once) and
    static layer (held all along) need more memory than the machine has."""
    ram = physical_memory() if ram is None else ram
    need = gop_bytes * max_decoded + static_bytes
    if ram is not None and need > ram:
        layer = f" and a static layer of {static_bytes / 2**30:.1f} GiB" if static_bytes else ""
        raise PlaybackError(f"decoding needs {need / 2**30:.1f} GiB ({max_decoded} GOPs of "
                            f"{gop_bytes / 2**30:.1f} GiB at once{layer}); this machine has {ram / 2**30:.1f} GiB")
