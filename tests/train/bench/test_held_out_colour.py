"""bench.training.held_out_colour's least-squares colour response, against direct computation on images."""

import math
import subprocess
import sys

import pytest
import torch

from bench.training.held_out_colour import IDENTITY, ColourSums, psnr_of
from stgs.metrics import psnr
from tests.conftest import PANOPTIC


def _images(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(12, 16, 3, generator=gen), torch.rand(12, 16, 3, generator=gen)


def test_fit_recovers_a_known_response_over_several_views():
    gain, offset = torch.tensor([0.9, 1.05, 1.1]), torch.tensor([0.04, -0.02, 0.0])
    sums = ColourSums()
    for seed in range(3):
        image, _ = _images(seed)
        sums += ColourSums.of(image, image * gain + offset)
    g, o = sums.fit()
    assert torch.allclose(g.float(), gain, atol=1e-6) and torch.allclose(o.float(), offset, atol=1e-6)
    assert sums.mse(g, o) < 1e-12 and psnr_of(0.0) == math.inf


def test_mse_matches_the_transformed_image_inside_a_mask():
    image, truth = _images()
    mask = torch.zeros(12, 16, dtype=torch.bool)
    mask[3:9, 2:11] = True
    gain, offset = torch.tensor([1.2, 0.8, 1.0], dtype=torch.float64), torch.tensor([-0.1, 0.05, 0.2],
                                                                                    dtype=torch.float64)
    sums = ColourSums.of(image, truth, mask)
    direct = ((image.double() * gain + offset - truth.double()) ** 2)[mask].mean().item()
    assert math.isclose(sums.mse(gain, offset), direct, rel_tol=1e-9)
    assert math.isclose(psnr_of(sums.mse(*IDENTITY)), psnr(image, truth, mask=mask), rel_tol=1e-9)


def test_fitted_response_is_never_worse_than_none():
    image, truth = _images(4)
    sums = ColourSums.of(image, truth)
    assert sums.mse(*sums.fit()) <= sums.mse(*IDENTITY)


def test_flat_render_and_empty_region_stay_finite_or_nan():
    _, truth = _images()
    flat = ColourSums.of(torch.full_like(truth, 0.5), truth)
    g, o = flat.fit()
    assert torch.equal(g, torch.ones(3, dtype=torch.float64))
    assert torch.allclose(o, truth.double().reshape(-1, 3).mean(0) - 0.5)
    assert math.isfinite(flat.mse(g, o))
    empty = ColourSums.of(truth, truth, torch.zeros(12, 16, dtype=torch.bool))
    assert math.isnan(empty.mse(g, o)) and math.isnan(psnr_of(empty.mse(g, o)))
    assert all(math.isfinite(v) for v in (*empty.fit()[0].tolist(), *empty.fit()[1].tolist()))


def test_an_unknown_camera_is_one_line_before_any_table():
    if not PANOPTIC.is_dir():
        pytest.skip("../shared/data/panoptic-basketball is absent")
    result = subprocess.run([sys.executable, "-m", "bench.training.held_out_colour", "--models", "no-such-scene",
                             "--dataset", str(PANOPTIC), "--cameras", "1,no-such-camera"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith("no camera(s) ['no-such-camera']")
