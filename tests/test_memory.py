"""Allocator tuning for the training loop."""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

import torch

from stgs.memory import reuse_large_allocations


def test_reuse_large_allocations_applies_on_glibc():
    on_glibc = platform.libc_ver()[0] == "glibc"
    assert reuse_large_allocations() is on_glibc
    big = torch.zeros(16, 1 << 20)  # 64 MiB from the heap now: still zero-filled, still usable
    big += 1
    assert bool(big.eq(1).all())


def test_filled_heap_fills_fresh_blocks_while_open():
    from stgs.memory import FilledHeap, filled_heap

    assert isinstance(filled_heap, FilledHeap)
    if platform.libc_ver()[0] != "glibc":
        assert not filled_heap.available
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    with filled_heap, filled_heap:  # nested (as concurrent encodes are): on until the last one closes
        pass
    assert filled_heap._open == 0
    with filled_heap:  # blocks past glibc's per-thread cache (1 KiB), which hands out small ones unfilled
        blocks = [libc.malloc(size) for size in (4096, 1 << 20)]
        try:
            for block, size in zip(blocks, (4096, 1 << 20), strict=True):
                assert ctypes.string_at(block, size) == bytes([FilledHeap.FILL ^ 0xFF]) * size
        finally:
            for block in blocks:
                libc.free(block)
