"""How the player shares the cores between the feature decoder and the renderer.

The renderer's kernels (deformation, projection, binning, compositing) are parallel loops over all the
threads torch is given; the feature decoder is one thread that decodes and dequantises one frame of the
next few (a few milliseconds each) and then sleeps until the renderer releases a frame. On few cores the
renderer keeps every core and the decoder runs in its gaps with a single libavcodec thread: HEVC frame
threading would add a frame of latency per thread and the decoder is rarely the bottleneck; from eight
cores on the decoder gets a second thread. docs/BENCHMARKS.md ("Real-time playback") measures the choice.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass

import torch


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


@dataclass(frozen=True)
class ThreadBudget:
    """Threads of each part of the frame path."""

    render: int
    """Threads of the deform and splat kernels (torch's intra-op thread count while playing)."""
    decode: int
    """libavcodec threads of the feature decoder (one decoder thread runs at a time)."""

    @classmethod
    def for_cores(cls, cores: int, render: int | None = None, decode: int | None = None) -> ThreadBudget:
        """The default budget for `cores` cores, with either part overridden."""
        cores = max(1, cores)
        return cls(render if render is not None else cores,
                   decode if decode is not None else (1 if cores < 8 else 2))


@contextlib.contextmanager
def render_threads(count: int) -> Iterator[None]:
    """Run the renderer with `count` torch threads, restoring the previous count afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
