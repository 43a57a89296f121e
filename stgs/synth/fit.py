"""Fit a GOP model to the procedural truth in parameter space (no rendering involved).

The canonical Gaussians are the truth at the GOP's first frame (opacity: its
maximum over the GOP, so fading is a negative ΔO). Temporal features (from
zero) and the deformation field are then optimised with Adam so that
deform(i, camera) reproduces the true attributes of every frame, the
view-dependent colour sampled from random camera centres around the scene.

Like the trainer (temporal and grid regularisers), the fit penalises features
that differ between grid neighbours and between consecutive frames: without
it Adam leaves noise-like features that the feature video spends about four
bits per sample on, at no gain in fidelity (docs/BENCHMARKS.md, "Synthetic
scene fit").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from stgs.model.gop import GOPModel, GOPShape, frame_time
from stgs.synth.scene import FoldedScene, ProceduralScene, TruthFrame

MAX_ROWS_PER_STEP = 32768
"""Gaussian x frame rows evaluated per optimisation step (bounds time and memory)."""


@dataclass
class FitResult:
    model: GOPModel
    """The fitted GOP."""
    position_rmse: float
    """RMSE of deformed means vs truth over all frames (scene units)."""
    color_rmse: float
    """RMSE of colours vs truth from the fit's camera centres."""
    opacity_rmse: float
    """RMSE of opacities vs truth."""


def _targets(model: GOPModel, truths: list[TruthFrame]) -> dict[str, torch.Tensor]:
    return {
        "dx": torch.stack([t.means for t in truths]) - model.xyz.detach(),
        "ds": torch.stack([t.log_scales for t in truths]) - model.log_scale.detach(),
        "dq": torch.stack([t.quats for t in truths]) - model.rotation.detach(),
        "opacity": torch.stack([t.opacities for t in truths]),
    }


def _init_canonical(model: GOPModel, truths: list[TruthFrame]) -> None:
    first = truths[0]
    peak = torch.stack([t.opacities for t in truths]).amax(0)
    with torch.no_grad():
        model.xyz.copy_(first.means)
        model.log_scale.copy_(first.log_scales)
        model.rotation.copy_(first.quats)
        model.opacity_logit.copy_(torch.logit(peak.clamp(1e-6, 1 - 1e-6)))
        model.color.copy_(first.base_colors)
        model.features.zero_()


def _predict(model: GOPModel, frames: torch.Tensor, idx: torch.Tensor, centers: torch.Tensor):
    """Deformed attributes for rows (frame, Gaussian) = frames x idx, cameras per frame."""
    w = model.shape.window
    rows_feat = torch.stack([model.features[f:f + w][:, idx].permute(1, 0, 2).reshape(len(idx), -1)
                             for f in frames.tolist()])
    n_f, n_g = len(frames), len(idx)
    t = torch.tensor([frame_time(f, model.shape.gop_size) for f in frames.tolist()])
    t_rows = t[:, None].expand(n_f, n_g).reshape(-1)
    xyz = model.xyz[idx].repeat(n_f, 1)
    cam_rows = centers[:, None, :].expand(n_f, n_g, 3).reshape(-1, 3)
    d_x, d_s, d_q, d_o, d_c = model.field(rows_feat.reshape(n_f * n_g, -1), t_rows, xyz, cam_rows)
    opacity = (torch.sigmoid(model.opacity_logit[idx]).repeat(n_f) + d_o).clamp(0.0, 1.0)
    color = torch.relu(model.color[idx]).repeat(n_f, 1) + d_c
    shape = (n_f, n_g)
    return (d_x.reshape(*shape, 3), d_s.reshape(*shape, 3), d_q.reshape(*shape, 4),
            opacity.reshape(shape), color.reshape(*shape, 3))


def random_centers(count: int, gen: torch.Generator, radius: float = 3.2) -> torch.Tensor:
    """Camera centres on a band of the sphere around the scene."""
    phi = 2 * math.pi * torch.rand(count, generator=gen)
    height = 0.3 + 2.0 * torch.rand(count, generator=gen)
    return torch.stack([radius * torch.sin(phi), height, radius * torch.cos(phi)], -1)


class _GridRoughness(torch.autograd.Function):
    """feature_roughness over every slot, its gradient written directly (a discrete Laplacian): about a
    tenth of the time of the gathered version and a third of the same expression left to autograd."""

    @staticmethod
    def forward(ctx, features: torch.Tensor, side: int) -> torch.Tensor:
        frames = features.shape[0]
        grid = features.reshape(frames, side, side, -1)
        right = grid[:, :, 1:] - grid[:, :, :-1]
        lower = grid[:, 1:] - grid[:, :-1]
        later = features[1:] - features[:-1]
        ctx.save_for_backward(right, lower, later)
        ctx.side = side
        spatial = (_squared_norm(right) + _squared_norm(lower)) / (2 * features.numel())
        return spatial + _squared_norm(later) / later.numel() if frames > 1 else spatial

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor) -> tuple[torch.Tensor, None]:
        right, lower, later = ctx.saved_tensors
        frames, side = right.shape[0], ctx.side
        grad = torch.zeros(frames, side, side, right.shape[-1], dtype=right.dtype)
        spatial = right.new_tensor(1.0 / grad.numel()) * grad_out
        for diff, head, tail in ((right * spatial, grad[:, :, 1:], grad[:, :, :-1]),
                                 (lower * spatial, grad[:, 1:], grad[:, :-1])):
            head += diff
            tail -= diff
        grad = grad.reshape(frames, side * side, -1)
        if frames > 1:
            temporal = later * (grad_out * (2.0 / later.numel()))
            grad[1:] += temporal
            grad[:-1] -= temporal
        return grad, None


def _squared_norm(t: torch.Tensor) -> torch.Tensor:
    flat = t.reshape(-1)
    return torch.dot(flat, flat)


def feature_roughness(features: torch.Tensor, side: int, anchors: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared difference of (E, S², C) features between each anchor slot (default: every slot) and its
    right and lower neighbours on the S x S grid (a slot on the last column or row is its own neighbour
    there), halved, plus between consecutive feature frames of the anchors. A random sample of anchors gives
    an unbiased estimate at a fraction of the cost on large grids (the fit samples the same slots as its
    data term); every slot (None) takes slices instead of a gather."""
    if features.shape[1] != side * side:
        raise ValueError(f"feature_roughness: {features.shape[1]} slots are not a {side} x {side} grid")
    if anchors is None:
        return _GridRoughness.apply(features, side)
    x, y = anchors % side, anchors // side
    right = torch.where(x < side - 1, anchors + 1, anchors)
    lower = torch.where(y < side - 1, anchors + side, anchors)
    own, right, lower = features[:, torch.cat([anchors, right, lower])].chunk(3, dim=1)  # one gather, one scatter
    spatial = ((right - own).square().mean() + (lower - own).square().mean()) / 2
    if features.shape[0] < 2:
        return spatial
    return spatial + (own[1:] - own[:-1]).square().mean()


def fit_gop(scene: ProceduralScene | FoldedScene, times: list[float], shape: GOPShape, steps: int,
            seed: int = 0, smoothness: float = 0.0) -> FitResult:
    """Fit one GOP to the truth at `times` (one per GOP frame); `smoothness` weighs feature_roughness."""
    if len(times) != shape.gop_size:
        raise ValueError("fit_gop: need one time per GOP frame")
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    model = GOPModel(shape)
    truths = [scene.at(t) for t in times]
    _init_canonical(model, truths)
    targets = _targets(model, truths)
    opt = torch.optim.Adam([{"params": [model.features], "lr": 2e-2},
                            {"params": model.field.parameters(), "lr": 4e-3}])
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, steps), eta_min=1e-4)
    n, g = shape.capacity, shape.gop_size
    frames_per_step = min(g, 8)
    gauss_per_step = min(n, max(1, MAX_ROWS_PER_STEP // frames_per_step))
    sampled = gauss_per_step < n  # else idx is every slot: the roughness runs on the whole grid, by slices
    for _ in range(steps):
        frames = torch.randperm(g, generator=gen)[:frames_per_step]
        idx = torch.randperm(n, generator=gen)[:gauss_per_step]
        centers = random_centers(frames_per_step, gen)
        d_x, d_s, d_q, opac, color = _predict(model, frames, idx, centers)
        true_color = torch.stack([truths[f].colors(c)[idx] for f, c in zip(frames.tolist(), centers,
                                                                          strict=True)])
        loss = (100 * (d_x - targets["dx"][frames][:, idx]).square().mean()
                + (d_s - targets["ds"][frames][:, idx]).square().mean()
                + 10 * (d_q - targets["dq"][frames][:, idx]).square().mean()
                + 10 * (opac - targets["opacity"][frames][:, idx]).square().mean()
                + 10 * (color - true_color).square().mean())
        if smoothness > 0:
            anchors = idx if sampled else None
            loss = loss + smoothness * feature_roughness(model.features, shape.grid_side, anchors)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    return _report(model, truths, targets, gen)


@torch.no_grad()
def _report(model: GOPModel, truths: list[TruthFrame], targets: dict[str, torch.Tensor],
            gen: torch.Generator) -> FitResult:
    idx = torch.arange(model.shape.capacity)
    sq = {"x": 0.0, "c": 0.0, "o": 0.0}
    for f in range(model.shape.gop_size):
        center = random_centers(1, gen)
        d_x, _, _, opac, color = _predict(model, torch.tensor([f]), idx, center)
        sq["x"] += (d_x[0] - targets["dx"][f]).square().mean().item()
        sq["c"] += (color[0] - truths[f].colors(center[0])).square().mean().item()
        sq["o"] += (opac[0] - targets["opacity"][f]).square().mean().item()
    g = model.shape.gop_size
    return FitResult(model, math.sqrt(sq["x"] / g), math.sqrt(sq["c"] / g), math.sqrt(sq["o"] / g))
