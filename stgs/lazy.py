"""Package attributes that load on first use (PEP 562), so that the light part of a package (configs, names)
does not pull in its heavy part (torch, PyAV)."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_attributes(package: str, homes: dict[str, str]) -> Callable[[str], object]:
    """A module-level __getattr__ for `package` that imports the module homes[name] when `name` is first read."""

    def attribute(name: str) -> object:
        if name in homes:
            return getattr(importlib.import_module(homes[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return attribute
