"""The native CPU kernels loaded (through cffi, typed by stgs.native.abi) for the modules that call them: the library,
whether it can run here, and the error when it cannot. stgs.native.build compiles it on first use.
"""

from __future__ import annotations

import os
from typing import Any

from stgs.errors import NativeUnavailableError
from stgs.native.build import build, library_path

__all__ = ["NativeUnavailableError", "available", "library_path", "load"]

_LIB: Any = None
_ERROR: str | None = None


def load() -> Any:
    """The loaded native library, its functions typed by csrc/stgs_abi.h (built on first use); raises
    NativeUnavailableError."""
    global _LIB, _ERROR
    if _LIB is not None:
        return _LIB
    if _ERROR is not None:
        raise NativeUnavailableError(_ERROR)
    if os.environ.get("STGS_NATIVE", "1") == "0":
        _ERROR = "disabled by STGS_NATIVE=0"
        raise NativeUnavailableError(_ERROR)
    try:
        from stgs.native.abi import ffi

        _LIB = ffi().dlopen(str(build()))
    except (NativeUnavailableError, OSError) as exc:
        _ERROR = str(exc)
        raise NativeUnavailableError(_ERROR) from exc
    return _LIB


def available() -> bool:
    try:
        load()
    except NativeUnavailableError:
        return False
    return True
