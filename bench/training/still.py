"""A still scene from one frame of a capture: what each training setting costs and buys
(`python -m bench.training.still`, prints Markdown rows for docs/BENCHMARKS.md).

Each row trains `stgs train --layers still` on frame `--frame` alone (the budget's config with `--set`'s overrides,
the `--holdout` cameras left out) in a fresh folder, packs it, and reports: the static layer's Gaussians, stage A's
wall time, the held-out cameras' PSNR and SSIM at that frame (the training report's, `stgs eval`'s figure), the
static segment's bytes and its render PSNR against the trained layer (the tree's stats.json), and the median time
`stgs play` takes to render one view of it (native splatter, a held-out camera, after a warm-up).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from bench.training.stage_a import parse_settings
from stgs.camera import read_scene_cameras
from stgs.model.renderer import StaticDrawer, render_still
from stgs.packaged import packaged_static
from stgs.packager import PackConfig, pack
from stgs.train import budget, train

RENDER_REPEATS = 5


def row(dataset: Path, frame: int, holdout: list[str], settings: dict, work: Path, budget_name: str) -> str:
    cfg = budget(budget_name, **({"layers": "still", "holdout": holdout, "start_frame": frame, "static_frames": 1}
                                 | settings))
    start = time.perf_counter()
    report = train(dataset, work / "model", cfg, progress=False)
    wall = time.perf_counter() - start
    stats = pack(work / "model", work / "tree", PackConfig(), progress=False)
    layer = packaged_static(work / "tree")
    assert layer is not None
    cam = next(c for c in read_scene_cameras(work / "tree") if c.name == holdout[0])
    drawer = StaticDrawer(layer)
    render_still(drawer, cam)  # warm-up: the drawer keeps the layer's per-view work, as a player does
    times = []
    for _ in range(RENDER_REPEATS):
        t0 = time.perf_counter()
        render_still(drawer, cam)
        times.append((time.perf_counter() - t0) * 1e3)
    label = ", ".join(f"{k} {v:g}" for k, v in settings.items()) or "the budget's"
    return (f"| {budget_name}: {label} | {layer.capacity:,} | {report['static_seconds']:.1f} ({wall:.1f}) | "
            f"{report['val_psnr']:.2f} | {report['val_ssim']:.3f} | {stats['static']['bytes'] / 1e3:.0f} | "
            f"{stats['static']['render_psnr']:.2f} | {statistics.median(times):.1f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--frame", type=int, default=0, help="the capture's frame the still is trained on")
    p.add_argument("--holdout", default="1,14,27")
    p.add_argument("--budget", action="append", default=[], help="a budget per row group (default: quick)")
    p.add_argument("--set", action="append", default=[], metavar="K=V,...",
                   help="one row's TrainConfig overrides (repeat for more rows; none: the budget's)")
    args = p.parse_args()
    holdout = args.holdout.split(",")
    settings = [parse_settings(s) for s in args.set] or [{}]
    print(f"machine: {platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}")
    print("| setting | Gaussians | stage A s (run s) | held-out PSNR dB | held-out SSIM | segment kB "
          "| segment vs layer dB | render ms |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.budget or ["quick"]:
        for s in settings:
            with tempfile.TemporaryDirectory() as tmp:
                print(row(args.dataset, args.frame, holdout, s, Path(tmp), name), flush=True)


if __name__ == "__main__":
    main()
