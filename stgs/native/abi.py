"""Typed bindings of the native library: cffi reads the declarations of csrc/stgs_abi.h, the one header every
kernel source includes, so Python and C++ see one signature per function (stgs.native.library.load opens the
library through it).

A call with the wrong number of arguments, or a tensor of the wrong dtype where the header wants `float *`,
`double *`, `int32_t *` or `int64_t *`, raises TypeError before anything runs (ctypes with hand-written
argtypes accepted any integer as a pointer); a definition that drifts from the header does not compile.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import torch
from cffi import FFI

from stgs.native.build import CSRC

ABI_HEADER = CSRC / "stgs_abi.h"
BEGIN, END = "// STGS_ABI_BEGIN", "// STGS_ABI_END"

POINTER_TYPES = {torch.float32: "float *", torch.float64: "double *", torch.int16: "int16_t *",
                 torch.int32: "int32_t *", torch.int64: "int64_t *"}
"""The C pointer type of each tensor dtype the ABI takes; others (bf16 tiles) go as `void *`."""


def declarations() -> str:
    """The ABI's function declarations (the header's text between its markers)."""
    text = ABI_HEADER.read_text()
    return text[text.index(BEGIN) + len(BEGIN):text.index(END)]


@cache
def ffi() -> FFI:
    interface = FFI()
    interface.cdef(declarations())
    return interface


def ptr(t: torch.Tensor | None) -> Any:
    """A pointer of the C type of `t`'s dtype to its data (NULL for None). `t` must be a contiguous CPU tensor
    and must outlive the call."""
    if t is None:
        return ffi().NULL
    if t.device.type != "cpu" or not t.is_contiguous():
        raise ValueError(f"native kernels take contiguous CPU tensors, got {t.device} "
                         f"{'contiguous' if t.is_contiguous() else 'strided'} {t.dtype}")
    return ffi().cast(POINTER_TYPES.get(t.dtype, "void *"), t.data_ptr())
