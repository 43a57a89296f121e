"""Dynamic-aware density: which pixels of a camera move (per-pixel std over frames above θ)."""

from __future__ import annotations

import torch


def dynamic_mask(frames: torch.Tensor, theta: float) -> torch.Tensor:
    """(H, W) bool: pixels whose luminance std over (F, H, W, 3) frames in [0, 1] exceeds theta."""
    if frames.ndim != 4 or frames.shape[0] < 2:
        raise ValueError("dynamic_mask needs (F >= 2, H, W, 3) frames")
    luma = frames.float() @ torch.tensor([0.299, 0.587, 0.114])
    return luma.std(dim=0) > theta


def spread_frames(num_frames: int, count: int) -> torch.Tensor:
    """`count` frame indices spread evenly over 0..num_frames-1 (all of them when count >= num_frames)."""
    if count >= num_frames:
        return torch.arange(num_frames)
    return torch.linspace(0, num_frames - 1, count).round().long()


def gop_dynamic_masks(images: torch.Tensor, count: int, theta: float) -> torch.Tensor:
    """(C, H, W) dynamic masks of a GOP's (F, C, H, W, 3) uint8 images from `count` frames spread over the whole
    GOP: motion in its last frames marks its pixels as much as motion in its first (a prefix of the GOP missed
    it). One camera at a time, so only `count` float frames are ever held."""
    pick = spread_frames(images.shape[0], count)
    return torch.stack([dynamic_mask(images[pick, c].float().div_(255.0), theta) for c in range(images.shape[1])])
