"""Dynamic-aware density: which pixels of a camera move (per-pixel luminance std over frames above θ), computed
one frame at a time (Welford's running variance), so a camera's whole span is never held at once."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from stgs.train.images import Views

LUMA = np.array([0.299, 0.587, 0.114])


def variance_mask(frames: Iterable[np.ndarray | torch.Tensor], theta: float) -> np.ndarray:
    """(H, W) bool: pixels whose luminance std (unbiased) over `frames` ((H, W, 3) RGB in [0, 1]) exceeds theta."""
    n = 0
    mean = m2 = np.zeros(0)
    for frame in frames:
        luma = np.asarray(frame, dtype=np.float64) @ LUMA
        n += 1
        if n == 1:
            mean, m2 = luma.copy(), np.zeros_like(luma)
            continue
        delta = luma - mean
        mean += delta / n
        m2 += delta * (luma - mean)
    if n < 2:
        raise ValueError("a dynamic mask needs at least two frames")
    return np.sqrt(m2 / (n - 1)) > theta


def gop_dynamic_masks(views: Views, count: int, theta: float) -> torch.Tensor:
    """(C, H, W) dynamic masks of a GOP's views from its first `count` frames, one view at a time."""
    frames = range(min(count, len(views.frames)))
    return torch.stack([torch.from_numpy(variance_mask((views.decoded(f, c) for f in frames), theta))
                        for c in range(len(views.cameras))])
