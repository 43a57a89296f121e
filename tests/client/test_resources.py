"""The player's peak-memory figure is its own, not that of the process that started it."""

from __future__ import annotations

import subprocess
import sys

import pytest

PARENT = r"""
import subprocess, sys
big = bytearray(1536 << 20)
big[::4096] = b"\x01" * len(big[::4096])  # touch every page: 1.5 GiB resident
child = ("import resource; from stgs.client.resources import process_peak_rss_mb; "
         "print(process_peak_rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)")
print(subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, check=True).stdout)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux's")
def test_a_player_started_by_a_large_process_reports_its_own_peak_memory():
    out = subprocess.run([sys.executable, "-c", PARENT], capture_output=True, text=True, check=True).stdout
    own, inherited = (float(v) for v in out.split())
    assert inherited >= 1536  # getrusage carries the parent's peak over exec: the trap this guards against
    assert 0 < own < 1200, own  # the child itself: Python and torch, well under the parent's 1.5 GiB
