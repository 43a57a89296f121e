"""bench.frame.static_tiles on a small layered model dir: it times frames whose images equal one splat of both
layers."""

from __future__ import annotations

import json

from bench.frame.static_tiles import measure
from stgs.camera import Camera, intrinsics, look_at
from stgs.model.store import save_model
from tests.model.test_gop import random_model
from tests.model.test_layers import random_static


def test_the_static_tiles_benchmark_times_equal_images(tmp_path):
    """bench.frame.static_tiles on a small layered model dir: one row, the kept layer's images checked against one
    splat of both layers on every timed frame (a difference ends the benchmark)."""

    save_model(tmp_path, [random_model(n=36, gop_size=4, seed=2)], 30.0, static=random_static(400, seed=1))
    cam = Camera("a", intrinsics(80, 60, 60.0), look_at((0.0, 0.3, -2.5), (0.0, 0.0, 0.0)), 80, 60)
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "cameras.json").write_text(json.dumps({"cameras": [cam.to_json()]}))
    (row,) = measure(tmp_path, frames=3, rounds=2)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:3] == [tmp_path.name, "400 + 36", "fp32"] and len(cells) == 11
    assert 0 <= float(cells[3].rstrip(" %")) <= 100
    assert all(float(c) > 0 for c in cells[4:7] + cells[8:])
