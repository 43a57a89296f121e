"""The native splatter's stages written in torch (its twins, as gsplat's `_torch_impl`), for per-stage parity
tests: each takes what the native stage takes and gives what it gives.

- projection: `stgs.render.project.project` (stage 1, csrc/project.cpp; autograd through it is the twin of
  stgs_project_backward);
- binning: `bin_tiles` (stage 2, csrc/binning.cpp): the same tile lists, id for id, from the same float64
  arithmetic in the same order;
- forward: `composite_tiles` (stage 3, csrc/forward.cpp): compositing of those lists, 16x16 tiles, with the
  per-pixel bookkeeping the backward pass reads;
- backward: autograd through `composite_tiles` (stage 4, csrc/backward.cpp).

The reference splatter (stgs.render.reference) is the oracle of whole images; these follow the kernel's own
structure (tiles of 16, ellipse-culled lists, pixel rects) so that a difference points at one stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from stgs.render.reference import tile_weights

TILE = 16
"""The native kernel's tile edge in pixels."""


@dataclass
class Bins:
    """Each tile's Gaussians front to back: ids[tile_start[t]:tile_start[t + 1]] for tile t = ty * tiles_x + tx."""

    tile_start: torch.Tensor
    """(tiles + 1,) int64 offsets into ids."""
    ids: torch.Tensor
    """(pairs,) int32 Gaussian indices."""
    tiles_x: int
    tiles_y: int

    def tile(self, t: int) -> torch.Tensor:
        return self.ids[self.tile_start[t]:self.tile_start[t + 1]]


def pixel_rects(means2d: torch.Tensor, extents: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(N, 4) inclusive pixel bounds u0, u1, v0, v1 whose centres lie within the screen extents (empty: u0 > u1
    or v0 > v1; culled Gaussians are empty)."""
    m, h = means2d.detach().double(), extents.detach().double()
    first = torch.ceil(m - h - 0.5)
    last = torch.floor(m + h - 0.5)
    size = torch.tensor([width, height], dtype=torch.float64)
    lo = torch.minimum(first, size).clamp(min=0)
    hi = torch.minimum(last, size - 1).clamp(min=-1)
    rect = torch.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], -1).long()
    culled = ~(extents.detach()[:, 0] >= 0)
    rect[culled] = torch.tensor([0, -1, 0, -1])
    return rect


def min_power(opacities: torch.Tensor) -> torch.Tensor:
    """ln(1 / (255 o)) - 1e-3 in float32, as the kernel's logf gives it (rounded from float64)."""
    level = torch.tensor(255.0, dtype=torch.float32) * opacities.detach().float()
    return -torch.log(level.double()).float() - torch.tensor(1e-3, dtype=torch.float32)


def tile_columns(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, rect: torch.Tensor,
                 ty: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last tile column (first > last: none) of each (Gaussian, tile row ty) pair: the columns holding a
    pixel centre inside the ellipse where alpha can reach 1/255, or the whole rect for degenerate conics."""
    a, b, c = (conics.detach()[:, i].float().double() for i in range(3))
    mx, my = means2d.detach()[:, 0].float().double(), means2d.detach()[:, 1].float().double()
    u0, u1, v0, v1 = rect.unbind(-1)
    det = a * c - b * b
    level = -2.0 * min_power(opacities).double() * (1.0 + 1e-3) + 1e-3
    narrow = torch.div(u0, TILE, rounding_mode="floor") == torch.div(u1, TILE, rounding_mode="floor")
    exact = ~narrow & (det > 0) & (a > 0) & (c > 0) & (level > 0)
    safe_det = torch.where(exact, det, torch.ones_like(det))
    y_reach = torch.sqrt(torch.where(exact, level * a / safe_det, torch.zeros_like(a)))
    dy_left = b * torch.sqrt(torch.where(exact, level * c / safe_det, torch.zeros_like(a))) / c
    inv_a = 1.0 / a
    row_lo = torch.maximum(ty * TILE, v0).double()
    row_hi = torch.minimum(ty * TILE + TILE - 1, v1).double()
    y0 = torch.maximum(row_lo + 0.5 - my, -y_reach)
    y1 = torch.minimum(row_hi + 0.5 - my, y_reach)

    def edge(dy: torch.Tensor, side: float) -> torch.Tensor:
        root = torch.sqrt(torch.clamp(a * level - det * dy * dy, min=0.0))
        return (-b * dy + side * root) * inv_a

    first = torch.ceil(mx + edge(torch.minimum(torch.maximum(dy_left, y0), y1), -1.0) - 0.5 - 1e-2)
    last = torch.floor(mx + edge(torch.minimum(torch.maximum(-dy_left, y0), y1), 1.0) - 0.5 + 1e-2)
    cu0 = torch.maximum(u0.double(), first)
    cu1 = torch.minimum(u1.double(), last)
    none = (y0 > y1) | (cu0 > cu1)
    ex0 = torch.where(none, torch.ones_like(u0), torch.div(cu0.nan_to_num(0).long(), TILE, rounding_mode="floor"))
    ex1 = torch.where(none, torch.zeros_like(u1), torch.div(cu1.nan_to_num(0).long(), TILE, rounding_mode="floor"))
    tx0 = torch.where(exact, ex0, torch.div(u0, TILE, rounding_mode="floor"))
    tx1 = torch.where(exact, ex1, torch.div(u1, TILE, rounding_mode="floor"))
    return tx0, tx1


def bin_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, depths: torch.Tensor,
              extents: torch.Tensor, width: int, height: int) -> Bins:
    """Stage 2: each tile's list of the on-screen Gaussians that can reach it, in depth order (float32 depth,
    index tie-break)."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    rect = pixel_rects(means2d, extents, width, height)
    visible = ((rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])).nonzero().squeeze(1)
    order = visible[torch.sort(depths.detach().float()[visible], stable=True).indices]
    rect = rect[order]
    ty0 = torch.div(rect[:, 2], TILE, rounding_mode="floor")
    rows = torch.div(rect[:, 3], TILE, rounding_mode="floor") - ty0 + 1
    row_owner = torch.repeat_interleave(torch.arange(len(order)), rows)
    row_start = torch.cumsum(rows, 0) - rows
    ty = ty0[row_owner] + torch.arange(len(row_owner)) - row_start[row_owner]
    g = order[row_owner]
    tx0, tx1 = tile_columns(means2d[g], conics[g], opacities[g], rect[row_owner], ty)
    cols = (tx1 - tx0 + 1).clamp(min=0)
    pair_row = torch.repeat_interleave(torch.arange(len(cols)), cols)
    col_start = torch.cumsum(cols, 0) - cols
    tx = tx0[pair_row] + torch.arange(len(pair_row)) - col_start[pair_row]
    tile = ty[pair_row] * tiles_x + tx
    rank = row_owner[pair_row]
    sorted_pairs = torch.sort(tile * max(1, len(order)) + rank).indices
    counts = torch.bincount(tile, minlength=tiles_x * tiles_y)
    tile_start = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(counts, 0)])
    return Bins(tile_start, order[rank[sorted_pairs]].to(torch.int32), tiles_x, tiles_y)


@dataclass
class Composite:
    """Stage 3's outputs."""

    image: torch.Tensor
    """(H, W, 3)."""
    trans_final: torch.Tensor
    """(H, W) transmittance left after the last contribution."""
    n_contrib: torch.Tensor
    """(H, W) int32: 1-based rank, in the pixel's tile list, of the last Gaussian composited (0: none)."""


def composite_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, colors: torch.Tensor,
                    background: torch.Tensor, extents: torch.Tensor, bins: Bins, width: int, height: int) -> Composite:
    """Stage 3: composite each tile's list front to back (alpha 0 outside a Gaussian's pixel rect, as the kernel
    never visits it); differentiable in means2d, conics, opacities, colours and background."""
    dtype = colors.dtype
    rect = pixel_rects(means2d, extents, width, height)
    image = torch.zeros(height, width, 3, dtype=dtype)
    trans_final = torch.ones(height, width, dtype=dtype)
    n_contrib = torch.zeros(height, width, dtype=torch.int32)
    for t in range(bins.tiles_x * bins.tiles_y):
        x0, y0 = (t % bins.tiles_x) * TILE, (t // bins.tiles_x) * TILE
        x1, y1 = min(width, x0 + TILE), min(height, y0 + TILE)
        ys, xs = torch.meshgrid(torch.arange(y0, y1), torch.arange(x0, x1), indexing="ij")
        px, py = xs.reshape(-1), ys.reshape(-1)
        ids = bins.tile(t).long()
        r = rect[ids]
        inside = ((px[None] >= r[:, 0, None]) & (px[None] <= r[:, 1, None])
                  & (py[None] >= r[:, 2, None]) & (py[None] <= r[:, 3, None]))
        pix = torch.stack([px, py], -1).to(dtype) + 0.5
        alpha, weights, added, left = tile_weights(means2d[ids].to(dtype), conics[ids].to(dtype),
                                                   opacities[ids].to(dtype), pix, inside)
        rank = torch.arange(1, len(ids) + 1, dtype=torch.int32)[:, None]
        last = (rank * (added & (alpha > 0))).amax(dim=0) if len(ids) else torch.zeros(len(px), dtype=torch.int32)
        colour = weights.T @ colors[ids].to(dtype) + left[:, None] * background[None, :].to(dtype)
        image[y0:y1, x0:x1] = colour.reshape(y1 - y0, x1 - x0, 3)
        trans_final[y0:y1, x0:x1] = left.reshape(y1 - y0, x1 - x0)
        n_contrib[y0:y1, x0:x1] = last.reshape(y1 - y0, x1 - x0).to(torch.int32)
    return Composite(image, trans_final, n_contrib)
