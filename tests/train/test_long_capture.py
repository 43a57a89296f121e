"""Long captures in bounded memory: views are decoded ahead through a cache of --max-memory bytes, never held
whole; the budget changes how often a view is decoded, never what a stage draws, so the model's bytes do not
depend on it; the training process's peak memory does not grow with the capture's length."""

from __future__ import annotations

import dataclasses
import json
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from stgs.cli.browser import served
from stgs.data import open_dataset
from stgs.synth import SynthConfig, synthesize
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.train import budget, train
from stgs.train.base import BASE_FILE
from stgs.train.images import open_views, quantised, smaller
from stgs.train.layers import moving_pixels
from stgs.tree import MANIFEST
from tests.conftest import run_stgs as stgs
from tests.train.conftest import LAYERED

MODEL_FILES = ("static.safetensors", "gop_0000.safetensors")


def test_the_cache_serves_every_drawn_view_as_decoded_under_a_tiny_budget(layered_scene):
    """A random plan over both levels, with room for three views: each sample is the view the dataset gives,
    scaled and masked as a direct read gives it, never another view left over in the cache."""
    ds = open_dataset(layered_scene)
    names = ds.camera_names[:-1]
    cam = ds.cameras(0)[0]
    view_bytes = cam.width * cam.height * 4
    views, held = open_views(ds, names, list(range(6)), 1.0, 3 * view_bytes, ds.camera_names[-1:])
    moving = moving_pixels(ds, views, 0.05)
    views.set_masks(moving)
    rng = random.Random(0)
    draws = [(rng.randrange(6), rng.randrange(len(names)), rng.randrange(2)) for _ in range(150)]
    views.plan(draws)
    for n, (f, c, level) in enumerate(draws):
        sample = views.at(level).sample(f, c)
        image = quantised(ds.pixels(f, names[c]), cam.width, cam.height)
        mask = moving(f, c)
        if level:
            image, mask = smaller(image, mask, sample.cam.width, sample.cam.height)
        assert np.array_equal(sample.target.mul(255).round().byte().numpy(), image), n
        assert np.array_equal(sample.dynamic.numpy(), mask), n
        if n % 10 == 0:  # the held-out camera's views, outside the plan, share the cache and have no masks
            assert held.dynamic_pixels(f, 0) is None
            truth = quantised(ds.pixels(f, ds.camera_names[-1]), cam.width, cam.height)
            assert np.array_equal(held.target(f, 0).mul(255).round().byte().numpy(), truth)
        assert views.source.cache.used <= 3 * view_bytes
    views.close()


def test_the_same_seed_gives_the_same_bytes_under_any_budget(layered_scene, tmp_path):
    """Stage A (with its half-size share and the view-dependent fit) and a GOP (half-size first) train to the
    same bytes with no view kept, three views kept, and every view kept."""
    cfg = budget("quick", **LAYERED, coarse_iterations=30, iterations=20, coarse_low_res=0.5, gop_low_res=0.5,
                 static_sh_degree=1, static_sh_iterations=10, threads=2)
    runs = {}
    for label, size in (("none", 0), ("three", 3 * 96 * 72 * 4), ("all", 1 << 30)):
        out = tmp_path / label
        report = train(layered_scene, out, dataclasses.replace(cfg, max_memory=size), progress=False)
        assert report["peak_rss_mb"] > 0
        runs[label] = [(out / name).read_bytes() for name in MODEL_FILES]
    assert runs["none"] == runs["three"] == runs["all"]


LONG = SynthConfig(grid_side=16, gop_size=60, num_gops=10, width=160, height=120, num_cameras=5, fit_steps=10,
                   effects=(*DEFAULT_EFFECTS, "static_background"), static_grid_side=16)
"""600 frames (20 s) of a small layered scene: 2,400 training views, 180 MB of pixels and masks held whole."""
BUDGET_MB = 8
GROWTH_MB = 40
"""What peak memory may grow by from 60 frames to 600 beyond the budget: the per-frame bookkeeping (draw lists,
masks per camera, the report) and allocator slack. Holding the views would add about 250 MB."""


def peak_training_mb(scene: Path, out: Path, gop_size: int) -> float:
    """`stgs train`'s own peak memory (VmHWM of its process, in its training report) on `scene` in two GOPs."""
    result = stgs("train", str(scene), str(out), "--budget", "quick", "--layers", "layered", "--grid-side", "12",
                  "--static-grid-side", "16", "--gop-size", str(gop_size), "--coarse-iterations", "40",
                  "--iterations", "10", "--threads", "2", "--max-memory", f"{BUDGET_MB}M", "--quiet")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "train_report.json").read_text())
    assert len(report["gops"]) == 2 and report["frames"] == gop_size * 2
    return report["peak_rss_mb"]


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="VmHWM is Linux's")
def test_peak_memory_does_not_grow_with_the_frame_count(tmp_path):
    """The same scene at 60 and 600 frames, two GOPs each (30 and 300 frames), under one budget."""
    short = tmp_path / "short"
    synthesize(dataclasses.replace(LONG, num_gops=1), short, progress=False)
    long = tmp_path / "long"
    synthesize(LONG, long, progress=False)
    small = peak_training_mb(short, tmp_path / "m60", 30)
    large = peak_training_mb(long, tmp_path / "m600", 300)
    assert large - small <= BUDGET_MB + GROWTH_MB, (small, large)


MINUTE = ["--seconds", "60", "--width", "32", "--height", "24", "--cameras", "3", "--grid-side", "8",
          "--static-grid-side", "8", "--fit-steps", "5", "--gop-size", "600", "--quiet",
          "--effects", "rigid,appear,static_background"]
"""A one-minute capture (1,800 frames in three 600-frame GOPs) at a small resolution."""
MINUTE_TRAIN = ["--budget", "quick", "--layers", "layered", "--grid-side", "8", "--static-grid-side", "8",
                "--gop-size", "600", "--coarse-iterations", "30", "--iterations", "10", "--threads", "1",
                "--max-memory", "4M", "--quiet"]


def test_a_one_minute_capture_trains_packs_serves_and_plays_to_its_end_locally_and_on_ray(tmp_path):
    """Trained here and on a local Ray instance to the same bytes, packed on Ray, served on loopback and played
    to its last frame (bench.training.long_capture packs and plays a 1,800-frame capture without Ray)."""
    scene = tmp_path / "minute"
    made = stgs("synth", str(scene), *MINUTE)
    assert made.returncode == 0, made.stderr
    assert open_dataset(scene).num_frames == 1800
    model = tmp_path / "model"
    trained = stgs("train", str(scene), str(model), *MINUTE_TRAIN)
    assert trained.returncode == 0, trained.stderr
    report = json.loads((model / "train_report.json").read_text())
    assert len(report["gops"]) == 3 and report["untrained_tail"] is None
    pytest.importorskip("ray")
    on_ray = tmp_path / "ray"
    ray_run = stgs("train", str(scene), str(on_ray), *MINUTE_TRAIN, "--ray", "local")
    assert ray_run.returncode == 0, ray_run.stderr
    for name in ("static.safetensors", *(f"gop_{k:04d}.safetensors" for k in range(3))):
        assert (on_ray / name).read_bytes() == (model / name).read_bytes(), name
    dash = tmp_path / "trees" / "minute"  # packed on Ray too (a local pack gives the same bytes: tests/tasks)
    packed = stgs("pack", str(on_ray), str(dash), "--qps", "32", "--ray", "local", "--quiet")
    assert packed.returncode == 0, packed.stderr
    log = tmp_path / "play.json"
    with served(dash.parent) as base:
        played = stgs("play", f"{base}minute/{MANIFEST}", "--log", str(log), "--size", "32x24", "--allow-loopback")
    assert played.returncode == 0, played.stderr
    doc = json.loads(log.read_text())
    assert doc["error"] is None and doc["gops_played"] == 3 and doc["frames"] == 1800


def test_a_run_killed_mid_stage_a_resumes_to_the_same_bytes(layered_scene, tmp_path):
    """SIGKILL once stage A has saved its first checkpoint (iteration 200 of 600), then --resume: the model is the
    uninterrupted run's, byte for byte."""
    flags = ["--budget", "quick", "--layers", "layered", "--gop-size", "6", "--grid-side", "12",
             "--static-grid-side", "16", "--coarse-iterations", "600", "--iterations", "20", "--threads", "2",
             "--max-memory", "64K", "--quiet"]
    whole = stgs("train", str(layered_scene), str(tmp_path / "whole"), *flags)
    assert whole.returncode == 0, whole.stderr
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "stgs.cli", "train", str(layered_scene), str(out), *flags],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoint, base = out / ".train" / "static.safetensors", out / ".train" / BASE_FILE
    deadline = time.monotonic() + 300
    while not checkpoint.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.kill()
    proc.wait()
    assert checkpoint.is_file() and not base.is_file(), "killed inside stage A, after its first checkpoint"
    resumed = stgs("train", str(layered_scene), str(out), *flags, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    for name in MODEL_FILES:
        assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
