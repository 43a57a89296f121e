"""Temporal features <-> 12-bit tiled video frames.

Each GOP's E feature grids (S x S x 16) are normalised per channel to [0, 1]
with the GOP's ranges, quantised to 12 bits and tiled 4 x 4 into one
4S x 4S single-channel frame per feature (channel c at tile row c // 4,
tile column c % 4).
"""

from __future__ import annotations

import numpy as np
import torch

from stgs.model.gop import FEATURE_DIM

TILES = 4
"""Tiles per side of a frame (TILES² = 16 channels)."""
VIDEO_BITS = 12
VIDEO_MAX = (1 << VIDEO_BITS) - 1


def feature_ranges(features: torch.Tensor) -> torch.Tensor:
    """(2, 16) per-channel [min, max] of (E, N, 16) features (a zero span is widened to 1e-6)."""
    lo = features.amin(dim=(0, 1))
    hi = features.amax(dim=(0, 1))
    hi = torch.where(hi - lo > 1e-6, hi, lo + 1e-6)
    return torch.stack([lo, hi]).float()


def quantize_features(features: torch.Tensor, ranges: torch.Tensor) -> torch.Tensor:
    """(E, N, 16) float -> int32 codes in [0, 4095]."""
    lo, hi = ranges[0], ranges[1]
    unit = ((features - lo) / (hi - lo)).clamp(0, 1)
    return torch.round(unit * VIDEO_MAX).to(torch.int32)


def dequantize_features(codes: torch.Tensor, ranges: torch.Tensor) -> torch.Tensor:
    """int codes (E, N, 16) -> float32 features."""
    lo, hi = ranges[0].float(), ranges[1].float()
    return codes.float().mul_((hi - lo) / VIDEO_MAX).add_(lo)


def tile_frames(codes: torch.Tensor, side: int) -> torch.Tensor:
    """(E, S², 16) codes -> (E, 4S, 4S) frames."""
    e = codes.shape[0]
    grid = codes.reshape(e, side, side, TILES, TILES)  # (e, y, x, tile_row, tile_col)
    return grid.permute(0, 3, 1, 4, 2).reshape(e, TILES * side, TILES * side)


def untile_frames(frames: torch.Tensor, side: int) -> torch.Tensor:
    """(E, 4S, 4S) frames -> (E, S², 16) codes."""
    e = frames.shape[0]
    grid = frames.reshape(e, TILES, side, TILES, side).permute(0, 2, 4, 1, 3)
    return grid.reshape(e, side * side, FEATURE_DIM)


def features_from_frames(frames: np.ndarray, side: int, ranges: torch.Tensor) -> torch.Tensor:
    """Decoded (E, 4S, 4S) uint16 12-bit frames -> (E, S², 16) float32 features (untile + dequantise)."""
    if frames.dtype != np.uint16 or frames.ndim != 3 or frames.shape[1:] != (TILES * side, TILES * side):
        raise ValueError(f"feature frames must be (E, {TILES * side}, {TILES * side}) uint16, "
                         f"got {frames.shape} {frames.dtype}")
    # 12-bit codes fit int16, which halves the memory traffic of the untiling copy.
    return dequantize_features(untile_frames(torch.from_numpy(frames.view(np.int16)), side), ranges)
