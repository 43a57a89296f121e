"""Image quality metrics."""

from __future__ import annotations

import math

import torch


def psnr(image: torch.Tensor, reference: torch.Tensor, peak: float = 1.0) -> float:
    """PSNR in dB of image vs reference (same shape, values in [0, peak]); inf when identical."""
    if image.shape != reference.shape:
        raise ValueError(f"psnr: shapes differ {tuple(image.shape)} vs {tuple(reference.shape)}")
    mse = (image.double() - reference.double()).square().mean().item()
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)
