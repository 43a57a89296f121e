"""bench.training.stage_a: its settings parser and one scored row on the layered test scene."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.training.stage_a import parse_settings, row
from stgs.data import open_dataset
from stgs.errors import StgsError


@pytest.fixture(scope="module")
def scene(layered_scene) -> Path:
    return layered_scene


def test_the_stage_a_benchmark_scores_the_static_layer_it_trains(scene, tmp_path):
    settings = parse_settings("gop_size=6,grid_side=12,static_grid_side=16,coarse_iterations=40,coarse_low_res=0.5,"
                              "lr.camera_colour=5e-4")
    assert settings == {"gop_size": 6, "grid_side": 12, "static_grid_side": 16, "coarse_iterations": 40,
                        "coarse_low_res": 0.5, "lr.camera_colour": 5e-4}
    held_out = open_dataset(scene).camera_names[-1]
    cells = row(scene, [held_out], settings, 0, tmp_path / "w", "quick").strip("| ").split(" | ")
    assert cells[:2] == ["gop_size 6, grid_side 12, static_grid_side 16, coarse_iterations 40, coarse_low_res 0.5, "
                         "lr.camera_colour 0.0005", "0"]
    with pytest.raises(StgsError, match="unknown learning rate"):
        row(scene, [held_out], {"lr.colour_camera": 1e-4}, 0, tmp_path / "bad", "quick")
    seconds, held_out_psnr, fitted_psnr = (float(c) for c in cells[2:])
    assert seconds >= 0 and 10 < held_out_psnr < 60 and 10 < fitted_psnr < 60
