"""bench.training.loss_terms: it times every variant of the image and projection terms and finds them equal."""

from __future__ import annotations

from bench.training.loss_terms import image_rows, projection_row


def test_the_loss_terms_benchmark_times_every_variant_and_finds_them_equal():
    for row in [*image_rows(1), projection_row(512, 1)]:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert len(cells) == 5
        assert all(float(ms) > 0 for ms in cells[2].split(" / "))
        assert float(cells[4].split()[0]) < 1e-5  # the variants compute the same values and gradients
