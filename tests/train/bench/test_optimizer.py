"""bench.training.optimizer: the fused Adam step against the per-parameter one, and whole iterations on a model
dir."""

from __future__ import annotations

import json

from bench.training.optimizer import measure, measure_iterations
from stgs.camera import Camera, intrinsics, look_at
from stgs.model.store import save_model
from stgs.tree import CAMERAS_FORMAT
from tests.model.test_gop import random_model
from tests.train.test_ops import SIDE


def test_the_fused_adam_step_is_the_per_parameter_one_up_to_rounding():
    """The trainer's Adam is torch's fused CPU kernel; bench.training.optimizer times it against the per-parameter loop
    and prints how far apart their parameters end (float32 rounding)."""
    cells = [c.strip() for c in measure(SIDE * SIDE, steps=3).strip("|").split("|")]
    assert cells[0] == f"{SIDE * SIDE}" and len(cells) == 6
    assert all(float(c) > 0 for c in cells[2:5])
    assert float(cells[5]) < 1e-6


def test_the_optimizer_benchmark_times_whole_iterations_on_a_model_dir(tmp_path):
    save_model(tmp_path, [random_model(n=SIDE * SIDE, gop_size=4, seed=2)], 30.0)
    cams = [Camera(name, intrinsics(80, 60, 60.0), look_at(eye, (0.0, 0.0, 0.0)), 80, 60)
            for name, eye in (("a", (0.0, 0.3, -2.5)), ("b", (0.6, 0.2, -2.4)))]
    doc = {"format": CAMERAS_FORMAT, "version": 1, "cameras": [c.to_json() for c in cams]}
    (tmp_path / "cameras.json").write_text(json.dumps(doc))
    cells = [c.strip() for c in measure_iterations(tmp_path, steps=3).strip("|").split("|")]
    assert cells[:2] == [tmp_path.name, f"{SIDE * SIDE}"] and len(cells) == 5
    assert all(float(c.split(" (")[0]) > 0 for c in cells[2:])
