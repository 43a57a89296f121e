"""stgs.packager: model dir -> MPEG-DASH tree (`stgs pack`); the profile is in manifests/PROFILE.md.

The settings (`PackConfig`) are light; the packer (torch, PyAV, OpenImageIO) loads on first use (PEP 562), so
that the command line reads the settings without it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from stgs.codec.video import DEFAULT_QPS
from stgs.lazy import lazy_attributes
from stgs.packager.config import PackConfig
from stgs.tree import MANIFEST, STATS

if TYPE_CHECKING:
    from stgs.packager.run import pack

__all__ = ["DEFAULT_QPS", "MANIFEST", "STATS", "PackConfig", "pack"]
__getattr__ = lazy_attributes(__name__, {"pack": "stgs.packager.run"})
