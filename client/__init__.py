"""stgs.client: the reference player (`stgs play`): manifest, downloader, ABR, pre-decode, CPU render, metrics."""

from stgs.client.config import PlaybackError, PlayConfig
from stgs.client.player import play

__all__ = ["PlayConfig", "PlaybackError", "play"]
