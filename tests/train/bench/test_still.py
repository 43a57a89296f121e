"""bench.training.still: one row on the one-frame capture of tests.conftest.still_scene."""

from __future__ import annotations

import pytest

from bench.training.still import row
from stgs.errors import StgsError
from tests.conftest import STILL_CAMERA


def test_the_still_benchmark_trains_packs_and_times_a_still(still_scene, tmp_path):
    cells = row(still_scene / "capture", 0, [STILL_CAMERA], {"coarse_iterations": 60, "static_grid_side": 8},
                tmp_path, "quick").strip("| ").split(" | ")
    assert cells[0] == "quick: coarse_iterations 60, static_grid_side 8" and cells[1] == "64"
    stage_a, run = (float(c) for c in cells[2].replace("(", "").replace(")", "").split())
    assert 0 < stage_a <= run
    psnr_db, ssim, kb, segment_db, render_ms = (float(c) for c in cells[3:])
    assert 5 < psnr_db < 60 and 0 < ssim <= 1 and kb > 0 and segment_db > 30 and render_ms > 0
    with pytest.raises(StgsError, match="no camera"):  # a camera the capture does not have
        row(still_scene / "capture", 0, ["nope"], {"coarse_iterations": 1}, tmp_path / "bad", "quick")
