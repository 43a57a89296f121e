"""The knobs of the PLAS sort (stgs.codec.plas), apart from the sort itself so that a config can name them
without loading torch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PLASConfig:
    """Knobs of the sort (docs/PACKAGING.md weighs its time against the bytes it saves)."""

    shrink: float = 0.9
    """Radius factor per level (closer to 1: more levels, smoother, slower)."""
    steps_per_radius: int = 4
    """Group-assignment steps per radius level."""
    min_radius: float = 1.0
    """Last radius."""
    seed: int = 0
    """Seed of the initial arrangement and the group offsets."""
    position_weight: float = 2.0
    """Weight of the position columns of the sort key."""
    feature_weight: float = 2.0
    """Weight of the temporal-feature columns (what the video codec sees)."""
