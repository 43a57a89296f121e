"""stgs.client: the reference player (`stgs play`): manifest, downloader, ABR, pre-decode, CPU render, metrics."""

from stgs.client.player import PlaybackError, PlayConfig, play

__all__ = ["PlayConfig", "PlaybackError", "play"]
