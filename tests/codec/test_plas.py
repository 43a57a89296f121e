"""PLAS: a permutation, deterministic, and much smoother than a random order."""

from __future__ import annotations

import torch

from stgs.codec.plas import blur, neighbour_distance, permute_gop, plas_order, sort_key
from stgs.codec.plas_config import PLASConfig
from stgs.model.renderer import FrameRenderer
from tests.model.test_gop import random_model


def test_order_is_a_deterministic_permutation():
    key = torch.randn(32 * 32, 5, generator=torch.Generator().manual_seed(0))
    a = plas_order(key, 32, PLASConfig(seed=3))
    b = plas_order(key, 32, PLASConfig(seed=3))
    assert torch.equal(a, b)
    assert torch.equal(a.sort().values, torch.arange(32 * 32))


def test_sorting_makes_neighbours_similar():
    """3-D points (a scene's positions) sort to a grid with neighbours 5x closer than at random."""
    gen = torch.Generator().manual_seed(1)
    key = torch.randn(48 * 48, 3, generator=gen)
    order = plas_order(key, 48)
    random = neighbour_distance(key[torch.randperm(48 * 48, generator=gen)], 48)
    assert neighbour_distance(key[order], 48) < 0.25 * random


def test_blur_preserves_constants():
    grid = torch.full((16, 16, 3), 2.5)
    assert torch.allclose(blur(grid, 3.0), grid)


def test_permuting_a_gop_does_not_change_its_images():
    model = random_model(n=256, gop_size=4)
    order = plas_order(sort_key(model), 16)
    sorted_model = permute_gop(model, order)
    assert torch.equal(sorted_model.features[:, 5], model.features[:, order[5]])
    from stgs.camera import Camera, intrinsics, look_at

    cam = Camera("c", intrinsics(40, 30, 50.0), look_at((0.0, 0.5, -3.0), (0.0, 0.0, 0.0)), 40, 30)
    a = FrameRenderer(model).render(2, cam)
    b = FrameRenderer(sorted_model).render(2, cam)
    assert (a - b).abs().max() < 1e-5  # only ties in depth order could differ
