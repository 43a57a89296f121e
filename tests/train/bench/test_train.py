"""bench.training.train's own parts: its evaluation rows and the labels that tell runs apart."""

from __future__ import annotations

import json
from pathlib import Path

from bench.training.train import distinct_labels, eval_rows, run_label


def test_bench_train_eval_rows_show_lpips_where_computed():
    view = {"frame": 0, "camera": "1", "psnr": 20.0, "ssim": 0.8}
    evaluation = {"streams": {
        "uncompressed": {"gops": [{"gop": 0, "psnr": 20.0, "ssim": 0.8, "lpips": 0.12345, "frames": [view] * 2}]},
        "qp16": {"gops": [{"gop": 0, "psnr": 19.5, "ssim": 0.79, "psnr_foreground": 17.0, "psnr_background": 21.0,
                           "frames": [view]}]}}}
    assert eval_rows("r", evaluation) == ["| r | uncompressed | 0 | 20.00 | 0.8000 | 0.1235 | - / - | 2 |",
                                          "| r | qp16 | 0 | 19.50 | 0.7900 | - | 17.00 / 21.00 | 1 |"]


def test_bench_train_labels_name_what_differs_from_the_budget(tmp_path):
    config = {"budget": "cpu", "grid_side": 192, "aux": False, "lr": {"position": 8e-4}, "init_frames": 12,
              "camera_colour": True}
    (tmp_path / "model.json").write_text(json.dumps({"extra": {"config": config}}))
    assert run_label(tmp_path) == "cpu: --no-aux, 36,864 Gaussians, init frames 12, position lr 0.0008"
    config["lr"] = {"position": 1.6e-4, "features": 5e-3, "field": 3.2e-3, "field_final": 3.2e-4}
    (tmp_path / "model.json").write_text(json.dumps({"extra": {"config": config}}))
    assert run_label(tmp_path).endswith("init frames 12, features lr 0.005, field lr 0.0032")
    config.update(grid_side=128, aux=True, lr={"position": 1.6e-4}, init_frames=6)
    (tmp_path / "model.json").write_text(json.dumps({"extra": {"config": config}}))
    assert run_label(tmp_path) == "cpu: all components"
    del config["init_frames"]  # a run from before the setting: its first frame only
    (tmp_path / "model.json").write_text(json.dumps({"extra": {"config": config}}))
    assert run_label(tmp_path) == "cpu: all components, init frames 1"
    config.update(init_frames=6, seed=1)
    (tmp_path / "model.json").write_text(json.dumps({"extra": {"config": config}}))
    assert run_label(tmp_path) == "cpu: all components, seed 1"


def test_bench_train_labels_a_run_from_before_a_component_as_trained_without_it(tmp_path):
    def label(config: dict) -> str:
        config = {"budget": "cpu", "init_frames": 6, **config}
        (tmp_path / "model.json").write_text(json.dumps({"extra": {"config": config}}))
        return run_label(tmp_path)

    assert label({"camera_colour": True}) == "cpu: all components"
    assert label({}) == "cpu: --no-camera-colour"  # before camera colours: trained without them
    layered = {"camera_colour": True, "layers": "layered", "migrate": True}
    assert label(layered) == "cpu: --no-hull-seeds --no-static-triangulation"
    assert label({**layered, "hull_seeds": True}) == "cpu: --no-static-triangulation"
    assert label({**layered, "hull_seeds": True, "static_triangulation": True}) == "cpu: all components"
    assert label({"camera_colour": True, "layers": "single"}) == "cpu: all components"  # no layers to miss them


def test_bench_train_tells_runs_with_the_same_settings_apart():
    dirs = [Path("/runs/new"), Path("/runs/old"), Path("/runs/seed1")]
    assert distinct_labels(dirs, ["cpu: --no-aux", "cpu: --no-aux", "cpu: --no-aux, seed 1"]) == [
        "cpu: --no-aux (new)", "cpu: --no-aux (old)", "cpu: --no-aux, seed 1"]
