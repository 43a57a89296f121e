"""Temporal features <-> tiled video frames of 12-bit (HEVC) or 10-bit (AV1) codes.

Each GOP's E feature grids (S x S x 16) are normalised per channel to [0, 1]
with the GOP's ranges, quantised to B bits (12 for the HEVC set, 10 for the
AV1 set: each set quantises the float features itself, so a 10-bit code is
round(unit * 1023), not a 12-bit code shifted; one range per channel, i.e.
per tile; no dither) and tiled 4 x 4 into one 4S x 4S single-channel frame
per feature (channel c at tile row c // 4, tile column c % 4).
"""

from __future__ import annotations

import numpy as np
import torch

from stgs.model.gop import FEATURE_DIM

TILES = 4
"""Tiles per side of a frame (TILES² = 16 channels)."""
VIDEO_BITS = 12
"""The HEVC set's code depth (the reference)."""
VIDEO_MAX = (1 << VIDEO_BITS) - 1
CODE_BITS = (10, 12)
"""The code depths a feature video may carry."""


def code_max(bits: int) -> int:
    """The largest code of a `bits`-bit feature frame."""
    if bits not in CODE_BITS:
        raise ValueError(f"feature codes are {' or '.join(map(str, CODE_BITS))} bits, not {bits}")
    return (1 << bits) - 1


def feature_ranges(features: torch.Tensor) -> torch.Tensor:
    """(2, 16) per-channel [min, max] of (E, N, 16) features (a zero span is widened to 1e-6)."""
    lo = features.amin(dim=(0, 1))
    hi = features.amax(dim=(0, 1))
    hi = torch.where(hi - lo > 1e-6, hi, lo + 1e-6)
    return torch.stack([lo, hi]).float()


def quantize_features(features: torch.Tensor, ranges: torch.Tensor, bits: int = VIDEO_BITS) -> torch.Tensor:
    """(E, N, 16) float -> int32 codes in [0, 2^bits - 1]."""
    lo, hi = ranges[0], ranges[1]
    unit = ((features - lo) / (hi - lo)).clamp(0, 1)
    return torch.round(unit * code_max(bits)).to(torch.int32)


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


def dequantize_frame(frame: np.ndarray, side: int, ranges: torch.Tensor,
                     out: torch.Tensor | None = None, bits: int = VIDEO_BITS) -> torch.Tensor:
    """One decoded (4S, 4S) uint16 frame of `bits`-bit codes -> (S², 16) float32 features (untile + dequantise), written
    into `out` when given. numpy on the calling thread only: the player runs this in its decoder thread
    beside the renderer, where torch's intra-op thread pool would compete for the renderer's cores."""
    if frame.dtype != np.uint16 or frame.shape != (TILES * side, TILES * side):
        raise ValueError(f"a feature frame must be ({TILES * side}, {TILES * side}) uint16, "
                         f"got {frame.shape} {frame.dtype}")
    out = torch.empty(side * side, FEATURE_DIM) if out is None else out
    if out.shape != (side * side, FEATURE_DIM) or out.dtype != torch.float32 or not out.is_contiguous():
        raise ValueError(f"dequantize_frame writes into a contiguous float32 ({side * side}, {FEATURE_DIM}) tensor")
    r = ranges.detach().to(torch.float32).numpy()
    lo, step = r[0], (r[1] - r[0]) / np.float32(code_max(bits))
    codes = frame.reshape(TILES, side, TILES, side).transpose(1, 3, 0, 2)  # (y, x, tile_row, tile_col)
    grid = out.numpy().reshape(side, side, TILES, TILES)
    np.multiply(codes, step.reshape(TILES, TILES), out=grid)
    np.add(grid, lo.reshape(TILES, TILES), out=grid)
    return out


def features_from_frames(frames: np.ndarray, side: int, ranges: torch.Tensor, bits: int = VIDEO_BITS) -> torch.Tensor:
    """Decoded (E, 4S, 4S) uint16 frames of `bits`-bit codes -> (E, S², 16) float32 features (dequantize_frame
    each)."""
    if frames.dtype != np.uint16 or frames.ndim != 3 or frames.shape[1:] != (TILES * side, TILES * side):
        raise ValueError(f"feature frames must be (E, {TILES * side}, {TILES * side}) uint16, "
                         f"got {frames.shape} {frames.dtype}")
    out = torch.empty(frames.shape[0], side * side, FEATURE_DIM)
    for frame, features in zip(frames, out, strict=True):
        dequantize_frame(frame, side, ranges, features, bits)
    return out
