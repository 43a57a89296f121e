"""bench.frame.splat_stages' count of the binned pairs that compositing reaches, which bounds the early-termination
lever: by hand on a rank map, and on a scene where an opaque front Gaussian saturates every tile."""

from __future__ import annotations

import pytest
import torch

from bench.frame.splat_stages import reached_pairs
from stgs.native.library import available
from stgs.render.native import raster_forward


def test_reached_pairs_is_the_largest_rank_per_tile():
    ranks = torch.zeros(20, 40, dtype=torch.int32)  # tiles: 2 rows (16 + 4 px) x 3 columns (16 + 16 + 8 px)
    ranks[3, 5] = 7
    ranks[10, 2] = 4  # the same tile: 7 counts, not 7 + 4
    ranks[17, 39] = 2  # the partial corner tile
    ranks[0, 16] = 1
    assert reached_pairs(ranks) == 7 + 2 + 1


@pytest.mark.skipif(not available(), reason="the native library could not be built here")
def test_an_opaque_front_gaussian_leaves_the_pairs_behind_it_unreached():
    width, height, behind = 64, 48, 50
    n = 1 + behind
    means2d = torch.tensor([[32.0, 24.0]]).repeat(n, 1)
    means2d[1:] += torch.rand(behind, 2, generator=torch.Generator().manual_seed(0)) * 8.0
    conics = torch.tensor([[1e-4, 0.0, 1e-4]]).repeat(n, 1)  # wide: every Gaussian covers the whole image
    opacities = torch.full((n,), 0.9)
    opacities[0] = 0.99  # alpha ~0.99 at the centre: transmittance falls below 1e-4 within a few layers
    depths = torch.arange(1, n + 1, dtype=torch.float32)
    extents = torch.full((n, 2), 200.0)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(1))
    _, handle = raster_forward(means2d, conics, opacities, colors, torch.zeros(3), depths, extents, width, height,
                               for_backward=True)
    tiles = (width // 16) * (height // 16)
    assert handle.pairs() == n * tiles  # every Gaussian binned to every tile
    reached = reached_pairs(handle.pixels()[1])
    assert tiles <= reached <= 6 * tiles < handle.pairs()  # of 51 per tile
