"""stgs.client: the reference player (`stgs play`): manifest, downloader, ABR, pre-decode, CPU render, metrics.

The player's entry points load on first use (PEP 562), so that `stgs.client.abr` and the other light modules
(the harness reads the ABR rules' names when it validates a scenario) do not import torch and PyAV."""

from __future__ import annotations

from typing import TYPE_CHECKING

from stgs.lazy import lazy_attributes

if TYPE_CHECKING:
    from stgs.client.config import PlaybackError, PlayConfig
    from stgs.client.session import play

__all__ = ["PlayConfig", "PlaybackError", "play"]
__getattr__ = lazy_attributes(__name__, {"PlayConfig": "stgs.client.config", "PlaybackError": "stgs.client.config",
                                         "play": "stgs.client.session"})
