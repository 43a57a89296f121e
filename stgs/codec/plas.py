"""PLAS: sort N = S² Gaussians into an S x S grid so that grid neighbours are similar.

Our implementation of Parallel Linear Assignment Sorting (Morgenstern et al.,
"Compact 3D Scene Representation via Self-Organizing Gaussian Grids"): start
from a random arrangement; for a radius shrinking from S/2 to 1, blur the grid
(the target each cell should resemble), then repeatedly split the grid into
disjoint groups of 4 cells (the corners of d x d squares, d <= radius, at a
random offset) and give every group the best of the 24 ways to place its 4
Gaussians on its 4 cells (closest to the blurred target). All groups are
solved at once with tensor ops, so a step costs O(N).

A smooth grid is what lets the attribute images and the feature video
compress: neighbouring pixels then hold similar Gaussians.
"""

from __future__ import annotations

import itertools
import math

import torch
import torch.nn.functional as F

from stgs.codec.plas_config import PLASConfig
from stgs.model.gop import GOPModel
from stgs.model.static import StaticLayer

PERMUTATIONS = torch.tensor(list(itertools.permutations(range(4))))
"""(24, 4): every placement of a group's 4 Gaussians on its 4 cells."""


DEFAULT_PLAS = PLASConfig()


def sort_key(model: GOPModel | StaticLayer, cfg: PLASConfig = DEFAULT_PLAS) -> torch.Tensor:
    """(N, D) standardised attributes a grid should be smooth in.

    Each attribute group (position, colour, log scale, rotation, opacity, the
    time-mean of the features where the model has them: a static layer has
    none) is standardised and scaled to equal weight, then position and
    features get their configured weights.
    """
    groups = [
        (model.xyz, cfg.position_weight),
        (model.color, 1.0),
        (model.log_scale, 1.0),
        (model.rotation, 1.0),
        (model.opacity_logit[:, None], 1.0),
    ]
    if isinstance(model, GOPModel):
        groups.append((model.features.mean(0), cfg.feature_weight))
    cols = []
    for values, weight in groups:
        v = values.detach().float()
        v = (v - v.mean(0)) / v.std(0).clamp_min(1e-6)
        cols.append(v * (weight / math.sqrt(v.shape[1])))
    return torch.cat(cols, dim=1)


def blur(grid: torch.Tensor, radius: float) -> torch.Tensor:
    """Separable Gaussian blur (sigma = radius, reflect padding) of an (S, S, D) grid."""
    side = grid.shape[0]
    half = min(side - 1, max(1, math.ceil(2 * radius)))
    x = torch.arange(-half, half + 1, dtype=grid.dtype)
    kernel = torch.exp(-0.5 * (x / radius) ** 2)
    kernel = (kernel / kernel.sum()).reshape(1, 1, -1)
    d = grid.shape[2]
    img = grid.permute(2, 0, 1).reshape(d * side, 1, side)  # rows
    img = F.conv1d(F.pad(img, (half, half), mode="reflect"), kernel)
    img = img.reshape(d, side, side).transpose(1, 2).reshape(d * side, 1, side)  # columns
    img = F.conv1d(F.pad(img, (half, half), mode="reflect"), kernel)
    return img.reshape(d, side, side).transpose(1, 2).permute(1, 2, 0)


def _group_view(t: torch.Tensor, d: int, m: int) -> torch.Tensor:
    """(m, m, ...) -> (groups, 4, ...): the corners of d x d squares tiling the m x m block."""
    rest = t.shape[2:]
    blocks = m // (2 * d)
    v = t[:m, :m].reshape(blocks, 2, d, blocks, 2, d, *rest)
    v = v.permute(0, 2, 3, 5, 1, 4, *range(6, 6 + len(rest)))
    return v.reshape(blocks * d * blocks * d, 4, *rest)


def _ungroup(g: torch.Tensor, d: int, m: int) -> torch.Tensor:
    rest = g.shape[2:]
    blocks = m // (2 * d)
    v = g.reshape(blocks, d, blocks, d, 2, 2, *rest)
    v = v.permute(0, 4, 1, 2, 5, 3, *range(6, 6 + len(rest)))
    return v.reshape(m, m, *rest)


def _assign_step(grid: torch.Tensor, index: torch.Tensor, target: torch.Tensor, d: int,
                 gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    side = grid.shape[0]
    m = (side // (2 * d)) * 2 * d
    oy, ox = (int(v) for v in torch.randint(0, side, (2,), generator=gen))
    shift = (-oy, -ox)
    g = torch.roll(grid, shift, dims=(0, 1))
    t = torch.roll(target, shift, dims=(0, 1))
    idx = torch.roll(index, shift, dims=(0, 1))
    xs = _group_view(g, d, m)           # (G, 4, D)
    ts = _group_view(t, d, m)           # (G, 4, D)
    # (G, 4 Gaussians, 4 cells); elementwise, not cdist's GEMM, so the result never depends on threading.
    cost = (xs[:, :, None, :] - ts[:, None, :, :]).square().sum(-1)
    total = cost[:, PERMUTATIONS, torch.arange(4)].sum(-1)  # (G, 24)
    best = PERMUTATIONS[total.argmin(1)]                      # (G, 4): Gaussian for each cell
    rows = torch.arange(xs.shape[0])[:, None]
    g[:m, :m] = _ungroup(xs[rows, best], d, m)
    idx[:m, :m] = _ungroup(_group_view(idx, d, m)[rows, best], d, m)
    return torch.roll(g, (oy, ox), dims=(0, 1)), torch.roll(idx, (oy, ox), dims=(0, 1))


def plas_order(key: torch.Tensor, side: int, cfg: PLASConfig = DEFAULT_PLAS) -> torch.Tensor:
    """Permutation p (N,) such that key[p] laid out row-major on an S x S grid is smooth."""
    n = key.shape[0]
    if n != side * side:
        raise ValueError(f"PLAS needs N = S² Gaussians, got N = {n} for S = {side}")
    gen = torch.Generator().manual_seed(cfg.seed)
    index = torch.randperm(n, generator=gen)
    grid = key[index].reshape(side, side, -1).clone()
    index = index.reshape(side, side)
    radius = side / 2
    while side >= 2:
        target = blur(grid, radius)
        for _ in range(cfg.steps_per_radius):
            d = int(torch.randint(1, max(1, min(int(radius), side // 2)) + 1, (1,), generator=gen))
            grid, index = _assign_step(grid, index, target, d, gen)
        if radius <= cfg.min_radius:
            break
        radius = max(cfg.min_radius, radius * cfg.shrink)
    return index.reshape(-1)


def neighbour_distance(key: torch.Tensor, side: int) -> float:
    """Mean distance between horizontally and vertically adjacent cells of the row-major grid."""
    grid = key.reshape(side, side, -1)
    dx = (grid[:, 1:] - grid[:, :-1]).norm(dim=-1)
    dy = (grid[1:] - grid[:-1]).norm(dim=-1)
    return torch.cat([dx.reshape(-1), dy.reshape(-1)]).mean().item()


def permute_gop(model: GOPModel, order: torch.Tensor) -> GOPModel:
    """A copy of `model` with its Gaussians in `order` (the rendered scene is unchanged)."""
    out = GOPModel(model.shape)
    state = model.state_dict()
    for name in ("xyz", "log_scale", "rotation", "opacity_logit", "color"):
        state[name] = state[name][order]
    state["features"] = state["features"][:, order]
    out.load_state_dict(state)
    return out


def permute_static(layer: StaticLayer, order: torch.Tensor) -> StaticLayer:
    """A copy of a static layer with its Gaussians in `order` (the rendered scene is unchanged)."""
    out = StaticLayer(layer.capacity, layer.sh_degree)
    out.load_state_dict({name: t[order] for name, t in layer.state_dict().items()})
    return out
