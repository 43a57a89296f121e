"""The initial scales' neighbour distances: exact, and in memory that grows with N."""

from __future__ import annotations

import pytest
import torch

from stgs.train.seeding import mean_neighbour_distance


def brute_force(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    d = torch.cdist(points.double(), points.double())
    d.fill_diagonal_(float("inf"))
    return d.topk(min(k, len(points) - 1), largest=False).values.mean(1).float()


def test_neighbour_distances_equal_the_full_distance_matrix_with_duplicates():
    points = torch.randn(500, 3, generator=torch.Generator().manual_seed(0))
    points[10] = points[11] = points[12]  # three equal points: each one's nearest two are at distance 0
    got = mean_neighbour_distance(points)
    assert torch.allclose(got, brute_force(points), rtol=1e-6, atol=1e-7)
    assert got[10] == pytest.approx(float(brute_force(points)[10]))
    assert 0 < got[10] < got.max()


@pytest.mark.parametrize("n", [2, 3, 4])
def test_few_points_use_all_the_others(n):
    points = torch.arange(n * 3, dtype=torch.float32).reshape(n, 3)
    assert torch.allclose(mean_neighbour_distance(points), brute_force(points))


def test_a_lone_point_gets_one_and_no_points_none():
    assert mean_neighbour_distance(torch.zeros(1, 3)).tolist() == [1.0]
    assert mean_neighbour_distance(torch.zeros(0, 3)).shape == (0,)


def test_the_paper_budgets_capacity_needs_no_distance_matrix():
    # 200,704 points (the paper budget's static layer, 448²): a full float32 distance matrix would be 161 GB.
    points = torch.rand(448 * 448, 3, generator=torch.Generator().manual_seed(1)) * 10
    got = mean_neighbour_distance(points)
    assert got.shape == (448 * 448,) and torch.isfinite(got).all() and (got > 0).all()
    sample = torch.arange(0, len(points), 997)
    exact = torch.cdist(points[sample].double(), points.double()).topk(4, largest=False).values[:, 1:].mean(1)
    assert torch.allclose(got[sample], exact.float(), rtol=1e-5)


@pytest.mark.parametrize("bad", [torch.zeros(4, 2), torch.tensor([[0.0, 0.0, float("nan")]] * 4)])
def test_bad_points_are_refused(bad):
    with pytest.raises(ValueError, match="points"):
        mean_neighbour_distance(bad)
