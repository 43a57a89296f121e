"""Allocator tuning for the training loop."""

from __future__ import annotations

import platform

import torch

from stgs.memory import reuse_large_allocations


def test_reuse_large_allocations_applies_on_glibc():
    on_glibc = platform.libc_ver()[0] == "glibc"
    assert reuse_large_allocations() is on_glibc
    big = torch.zeros(16, 1 << 20)  # 64 MiB from the heap now: still zero-filled, still usable
    big += 1
    assert bool(big.eq(1).all())
