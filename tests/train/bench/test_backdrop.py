"""bench.training.backdrop on a small layered model dir: it times training steps equal to the one-splat step."""

from __future__ import annotations

import json

from bench.training.backdrop import measure
from stgs.camera import Camera, intrinsics, look_at
from stgs.model.store import save_model
from stgs.tree import CAMERAS_FORMAT
from tests.model.test_gop import random_model
from tests.model.test_layers import random_static


def test_the_backdrop_benchmark_times_equal_training_steps(tmp_path):
    """bench.training.backdrop on a small layered model dir: one row, each kept step checked against the one-splat step
    (image and colour gradients; a difference ends the benchmark)."""

    save_model(tmp_path, [random_model(n=36, gop_size=4, seed=2)], 30.0, static=random_static(400, seed=1))
    cams = [Camera(name, intrinsics(80, 60, 60.0), look_at(eye, (0.0, 0.0, 0.0)), 80, 60)
            for name, eye in (("a", (0.0, 0.3, -2.5)), ("b", (0.6, 0.2, -2.4)))]
    doc = {"format": CAMERAS_FORMAT, "version": 1, "cameras": [c.to_json() for c in cams]}
    (tmp_path / "cameras.json").write_text(json.dumps(doc))
    row = measure(tmp_path, steps=3, rounds=2)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:2] == [tmp_path.name, "400 + 36"] and len(cells) == 7
    assert 0 < float(cells[2].split(" %")[0]) <= 100
    assert all(float(c) > 0 for c in cells[3:])
