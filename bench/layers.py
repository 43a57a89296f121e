"""Layered scenes (model format 2) against single-layer ones: render cost per frame and quality per training
second (`python -m bench.layers`, prints Markdown rows for docs/BENCHMARKS.md).

1. Render cost: deform + splat ms per frame (native path) of a single-layer GOP of N Gaussians against a
   static layer of N_s plus a dynamic layer of N_d, the static layer's per-view work reused while the camera
   stays (a still viewer) or redone every frame (a moving one). Gaussians: the synthetic scene's truth
   (backdrop for the static layer), random deformation weights scaled small. Medians after a warm-up.
2. Quality per training second: `stgs train` (quick budget) single vs layered vs layered without migration
   on a synthetic scene with a static background, `stgs eval` on its held-out camera (whole frame, inside
   and outside the foreground masks).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from stgs.camera import Camera, look_at
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.view import FrameRenderer
from stgs.synth import SynthConfig, ground_truth_cameras, synthesize, truth_static_layer
from stgs.synth.scene import DEFAULT_EFFECTS, ProceduralScene


def gop_from_truth(n: int, gop_size: int = 60, seed: int = 0) -> GOPModel:
    truth = ProceduralScene(n, DEFAULT_EFFECTS, seed).at(0.0)
    model = GOPModel(GOPShape(n, gop_size))
    gen = torch.Generator().manual_seed(seed)
    truth.copy_into(model, 1e-4)
    with torch.no_grad():
        model.features.copy_(torch.randn(model.features.shape, generator=gen) * 0.1)
        for p in model.field.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.02)
    return model


def frame_ms(renderer: FrameRenderer, cameras: list[Camera], frames: int, moving: bool) -> float:
    times = []
    for i in range(frames + 1):
        cam = cameras[i % len(cameras)] if moving else cameras[0]
        start = time.perf_counter()
        renderer.render(i % renderer.model.shape.gop_size, cam)
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times[1:])


def render_rows(single: int, static: int, dynamic: int, width: int, height: int, frames: int) -> list[str]:
    cfg = SynthConfig(width=width, height=height, num_cameras=8)
    cams = ground_truth_cameras(cfg)
    path = [Camera(f"p{i}", cams[0].K, look_at((3.2 * torch.cos(torch.tensor(0.01 * i)).item(), 1.4,
                                                 3.2 * torch.sin(torch.tensor(0.01 * i)).item()), (0.0, 0.55, 0.0)),
                   width, height) for i in range(frames + 1)]
    scene = ProceduralScene(dynamic, (*DEFAULT_EFFECTS, "static_background"), 0, static)
    layered = FrameRenderer(gop_from_truth(dynamic), static=truth_static_layer(scene))
    flat = FrameRenderer(gop_from_truth(single))
    rows = []
    for label, renderer, n in (("single layer", flat, f"{single:,}"),
                               ("layered", layered, f"{static:,} + {dynamic:,}")):
        still = frame_ms(renderer, path, frames, moving=False)
        moving = frame_ms(renderer, path, frames, moving=True)
        rows.append(f"| {label} | {n} | {still:.1f} | {moving:.1f} |")
    return rows


def train_rows(work: Path, iterations: int, coarse: int) -> list[str]:
    scene = work / "scene"
    synthesize(SynthConfig(grid_side=16, num_gops=1, gop_size=6, width=96, height=72, num_cameras=8, fit_steps=30,
                           effects=(*DEFAULT_EFFECTS, "static_background"), static_grid_side=16), scene,
               progress=False)
    stgs = [str(Path(sys.executable).with_name("stgs"))]
    runs = {"single (S = 24)": ["--layers", "single", "--grid-side", "24"],
            "layered (S_s = 24, S_d = 16)": ["--layers", "layered"],
            "layered, --no-migrate": ["--layers", "layered", "--no-migrate"]}
    rows = []
    for label, flags in runs.items():
        out = work / label.split()[0] / str(len(rows))
        subprocess.run([*stgs, "train", str(scene), str(out), "--gop-size", "6", "--iterations", str(iterations),
                        "--coarse-iterations", str(coarse), "--quiet", *flags], check=True, capture_output=True)
        subprocess.run([*stgs, "eval", str(out), str(scene), "--out", str(out / "ev"), "--quiet"], check=True,
                       capture_output=True)
        report = json.loads((out / "train_report.json").read_text())
        ev = json.loads((out / "ev" / "eval.json").read_text())
        s = ev["streams"]["uncompressed"]
        gop_s = sum(g["seconds"] for g in report["gops"])
        first = report.get("static_seconds", report["coarse_seconds"])
        g = ev["gaussians"]
        rows.append(f"| {label} | {g['static']:,} + {g['dynamic']:,} | {first:.1f} | {gop_s:.1f} | "
                    f"{s['psnr']:.2f} | {s['ssim']:.4f} | {s['psnr_foreground']:.2f} / {s['psnr_background']:.2f} | "
                    f"{report.get('migrated', '-')} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--single", type=int, default=16384)
    parser.add_argument("--static", type=int, default=25600)
    parser.add_argument("--dynamic", type=int, default=9216)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--coarse-iterations", type=int, default=1000)
    parser.add_argument("--skip-train", action="store_true")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}")
    print("| scene | Gaussians (static + dynamic) | ms/frame, still camera | ms/frame, moving camera |")
    print("|---|---|---|---|")
    print("\n".join(render_rows(args.single, args.static, args.dynamic, 640, 360, args.frames)))
    if args.skip_train:
        return
    print()
    print("| run | Gaussians (static + dynamic) | coarse / stage A s | GOP s | held-out PSNR | SSIM | "
          "foreground / background PSNR | migrated |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        print("\n".join(train_rows(Path(tmp), args.iterations, args.coarse_iterations)))


if __name__ == "__main__":
    main()
