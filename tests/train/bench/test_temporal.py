"""bench.training.temporal: it times four variants of the temporal loss and compares their gradients."""

from __future__ import annotations

from bench.training.temporal import measure


def test_the_temporal_benchmark_times_four_variants_and_compares_their_gradients():
    cells = [c.strip() for c in measure(64, steps=2).strip("|").split("|")]
    assert cells[0] == "64" and len(cells) == 7
    assert all(float(c) > 0 for c in cells[1:6])
    assert float(cells[6]) < 1e-9  # the hand-written and the native backward are autograd's gradient
