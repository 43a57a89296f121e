"""Pure-torch reference splatter: the oracle the native kernel is tested against.

Short and literal on purpose. Each screen tile composites its depth-sorted
Gaussians densely (K Gaussians x P pixels), which is exactly the per-pixel
front-to-back loop of docs/ARCHITECTURE.md written with cumulative products.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from stgs.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected

REFERENCE_TILE = 32
"""Tile edge of the reference (bigger tiles: fewer Python iterations, more dense work)."""


def tile_weights(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, pix: torch.Tensor,
                 inside: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The splatter's front-to-back loop (docs/ARCHITECTURE.md) for depth-sorted Gaussians (K, ...) over pixel
    centres pix (P, 2):
    (alpha, weight of each contribution, added, final transmittance), the first three (K, P), the last (P,).
    `inside` (K, P), where given, zeroes alpha outside it (the native kernel's pixel rects)."""
    d = pix[None, :, :] - means2d[:, None, :]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = (conics[:, i, None] for i in range(3))
    # The quadratic form is non-negative; the clamp only guards float rounding.
    power = (-0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)).clamp(max=0.0)
    alpha = (opacities[:, None] * torch.exp(power)).clamp(max=ALPHA_MAX)
    keep = alpha >= ALPHA_MIN if inside is None else (alpha >= ALPHA_MIN) & inside
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    trans_after = torch.cumprod(1.0 - alpha, dim=0)
    added = trans_after >= T_MIN  # a prefix along K: transmittance never rises
    trans_before = torch.cat([torch.ones_like(trans_after[:1]), trans_after[:-1]], dim=0)
    weights = alpha * trans_before * added
    trans_final = torch.where(added, 1.0 - alpha, torch.ones_like(alpha)).prod(dim=0)
    return alpha, weights, added, trans_final


def composite_tile(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                   colors: torch.Tensor, pix: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Composite depth-sorted Gaussians (K, ...) over pixel centres pix (P, 2) -> (P, 3)."""
    _, weights, _, trans_final = tile_weights(means2d, conics, opacities, pix)
    return weights.T @ colors + trans_final[:, None] * background[None, :]


def tile_members(means2d: torch.Tensor, extents: torch.Tensor, x0: int, x1: int, y0: int,
                 y1: int) -> torch.Tensor:
    """Indices of Gaussians whose alpha can reach 1/255 at a pixel centre in [x0,x1)x[y0,y1)."""
    mx, my = means2d[:, 0].detach(), means2d[:, 1].detach()
    hx, hy = extents[:, 0], extents[:, 1]
    hit = ((hx >= 0) & (mx + hx >= x0 + 0.5) & (mx - hx <= x1 - 0.5)
           & (my + hy >= y0 + 0.5) & (my - hy <= y1 - 0.5))
    return hit.nonzero().squeeze(1)


def composite_reference(proj: Projected, opacities: torch.Tensor, colors: torch.Tensor, width: int,
                        height: int, background: torch.Tensor, tile: int = REFERENCE_TILE,
                        cull: bool = True) -> torch.Tensor:
    """Composite projected Gaussians into an (H, W, 3) image.

    cull=False composites every Gaussian at every pixel (no screen extents),
    which tests use to show that tiling never changes the image.
    """
    dtype = colors.dtype
    # float32 keys with index tie-break: the exact order the native kernel uses.
    order = torch.sort(proj.depths.detach().float(), stable=True).indices
    order = order[proj.extents[order, 0] >= 0]
    means2d = proj.means2d[order].to(dtype)
    conics = proj.conics[order].to(dtype)
    opac, cols, ext = opacities[order], colors[order], proj.extents[order]
    if not cull:
        ext = torch.full_like(ext, float("inf"))
    use_checkpoint = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, opac, cols, background))
    rows = []
    for y0 in range(0, height, tile):
        y1 = min(height, y0 + tile)
        row = []
        for x0 in range(0, width, tile):
            x1 = min(width, x0 + tile)
            ys, xs = torch.meshgrid(torch.arange(y0, y1, dtype=dtype) + 0.5,
                                    torch.arange(x0, x1, dtype=dtype) + 0.5, indexing="ij")
            pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)
            idx = tile_members(means2d, ext, x0, x1, y0, y1)
            args = (means2d[idx], conics[idx], opac[idx], cols[idx], pix, background)
            out = checkpoint(composite_tile, *args, use_reentrant=False) if use_checkpoint \
                else composite_tile(*args)
            row.append(out.reshape(y1 - y0, x1 - x0, 3))
        rows.append(torch.cat(row, dim=1))
    return torch.cat(rows, dim=0)
