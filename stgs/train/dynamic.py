"""Dynamic-aware density: which pixels of a camera move (per-pixel std over frames above θ)."""

from __future__ import annotations

import torch


def dynamic_mask(frames: torch.Tensor, theta: float) -> torch.Tensor:
    """(H, W) bool: pixels whose luminance std over (F, H, W, 3) frames in [0, 1] exceeds theta."""
    if frames.ndim != 4 or frames.shape[0] < 2:
        raise ValueError("dynamic_mask needs (F >= 2, H, W, 3) frames")
    luma = frames.float() @ torch.tensor([0.299, 0.587, 0.114])
    return luma.std(dim=0) > theta
