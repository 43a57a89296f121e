"""Training losses of the paper (each a small function with a hand-checkable value; tests/train/test_losses.py)."""

from __future__ import annotations

import torch

from stgs.metrics import masked_mean, ssim
from stgs.native.abi import ptr
from stgs.native.library import available, load


def photometric(image: torch.Tensor, target: torch.Tensor, lambda_ssim: float = 0.2,
                mask: torch.Tensor | None = None, ssim_values: torch.Tensor | None = None) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM), over the pixels of `mask` ((H, W) bool) when given; `ssim_values` is
    ssim_map(image, target) when the caller already has it (the full and the masked term share it)."""
    diff = (image - target).abs()
    if mask is not None:
        if not mask.any():
            return image.sum() * 0.0
        l1 = masked_mean(diff.sum(-1), mask) / diff.shape[-1]
    else:
        l1 = diff.mean()
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim(image, target, mask, ssim_values))


class _TemporalHuber(torch.autograd.Function):
    """Mean Huber penalty of e_{i+1} − e_i with a hand-written backward: one gradient buffer, where autograd's
    two slices of the whole feature tensor are each zero-filled and then summed (bench.training.temporal measures
    both; docs/BENCHMARKS.md, "Training steps")."""

    @staticmethod
    def forward(ctx, features: torch.Tensor, delta: float) -> torch.Tensor:
        diff = features[1:] - features[:-1]
        ctx.save_for_backward(diff)
        ctx.delta = delta
        return torch.nn.functional.huber_loss(diff, diff.new_zeros(()).expand_as(diff), delta=delta)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor) -> tuple[torch.Tensor, None]:
        (diff,) = ctx.saved_tensors
        slope = diff.clamp(-ctx.delta, ctx.delta)  # the Huber penalty's derivative
        grad = diff.new_empty((diff.shape[0] + 1, *diff.shape[1:]))
        torch.neg(slope[0], out=grad[0])
        grad[-1] = slope[-1]
        torch.sub(slope[:-1], slope[1:], out=grad[1:-1])
        return grad.mul_(grad_out / diff.numel()), None


def temporal_huber(features: torch.Tensor, delta: float = 0.01) -> torch.Tensor:
    """Mean Huber penalty of consecutive feature differences e_{i+1} − e_i of (E, N, C) features."""
    if features.shape[0] < 2:
        return features.sum() * 0.0
    return _TemporalHuber.apply(features, delta)


class _NativeWindowAndHuber(torch.autograd.Function):
    """The frame's window features[first:first + window] (a copy) and temporal_huber(features) in native
    kernels (csrc/temporal.cpp), the two gradients written as one buffer in one pass: autograd's slice of the
    whole tensor zero-fills a second full-size gradient and adds it to the Huber term's (bench.training.temporal)."""

    @staticmethod
    def forward(ctx, features: torch.Tensor, first: int, window: int, delta: float):
        features = features.detach().contiguous()
        rows, cols = features.shape[0], features[0].numel()
        total = load().stgs_temporal_huber_forward(rows, cols, ptr(features), delta, torch.get_num_threads())
        ctx.save_for_backward(features)
        ctx.first, ctx.window, ctx.delta = first, window, delta
        block = features[first:first + window].clone()
        return block, torch.tensor(total / ((rows - 1) * cols), dtype=features.dtype)

    @staticmethod
    def backward(ctx, grad_block: torch.Tensor | None, grad_value: torch.Tensor | None):
        (features,) = ctx.saved_tensors
        rows, cols = features.shape[0], features[0].numel()
        scale = 0.0 if grad_value is None else float(grad_value) / ((rows - 1) * cols)
        block = None if grad_block is None else grad_block.to(torch.float32).contiguous()
        grad = torch.empty_like(features)
        load().stgs_temporal_huber_backward(rows, cols, ptr(features), ctx.delta, scale, ptr(block), ctx.first,
                                            ctx.window, ptr(grad), torch.get_num_threads())
        return grad, None, None, None


def window_and_temporal_huber(features: torch.Tensor, first: int, window: int, delta: float = 0.01,
                              backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """The (window, N, C) block features[first:first + window] of (E, N, C) features and
    temporal_huber(features, delta), with gradients to `features` through both. `backend` "auto" takes float32
    CPU features with at least two frames through the native kernels (one gradient buffer written once), others,
    and "torch" always, through the slice and temporal_huber."""
    if backend not in ("auto", "torch"):
        raise ValueError(f"window_and_temporal_huber: unknown backend {backend!r}; use 'auto' or 'torch'")
    if not 0 <= first <= features.shape[0] - window or window < 1:
        raise ValueError(f"window_and_temporal_huber: window {first}..{first + window - 1} is outside the "
                         f"{features.shape[0]} frames of features")
    if backend == "auto" and features.shape[0] >= 2 and features.dtype == torch.float32 and \
            features.device.type == "cpu" and available():
        block, value = _NativeWindowAndHuber.apply(features, first, window, delta)
        return block, value
    return features[first:first + window], temporal_huber(features, delta)


def self_distillation(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Mean squared distance of the MLP's hidden state to the transformer's (teacher held fixed)."""
    return (student - teacher.detach()).square().mean()


def opacity_l1(opacities: torch.Tensor) -> torch.Tensor:
    """Mean opacity (opacities are non-negative): pushes unneeded Gaussians to 0 so they can be relocated."""
    return opacities.abs().mean()


def grid_smoothness(values: torch.Tensor, side: int) -> torch.Tensor:
    """Mean squared difference of 4-neighbours of (S², C) attributes laid out as the S x S PLAS grid."""
    grid = values.reshape(side, side, -1)
    return ((grid[1:] - grid[:-1]).square().mean() + (grid[:, 1:] - grid[:, :-1]).square().mean()) / 2
