"""Layered scenes (model format 2) against single-layer ones: render cost per frame and quality per training
second (`python -m bench.training.layers`, prints Markdown rows for docs/BENCHMARKS.md).

1. Render cost: deform + splat ms per frame (native path) of a single-layer GOP of N Gaussians against a
   static layer of N_s plus a dynamic layer of N_d, the static layer's per-view work reused while the camera
   stays (a still viewer) or redone every frame (a moving one). Gaussians: the synthetic scene's truth
   (backdrop for the static layer), random deformation weights scaled small. Medians after a warm-up.
2. Quality per training second: `stgs train` (quick budget) single vs layered vs layered without migration
   on a synthetic scene with a static background, `stgs eval` on its held-out camera (whole frame, inside
   and outside the foreground masks).
3. With `--models DIR,... --dataset D`: trained scenes' Gaussians per layer (live: opacity above the dead
   threshold 0.02), deform + splat ms per frame over their first GOP from one camera (`--camera`), and the
   PSNR of the background far from the players (outside the dataset's masks grown by FAR_PX) at every 10th
   frame of the cameras they were not trained on: the static layer's own error, without the players' edges
   and shadows; and the PSNR inside the masks (the players) from every PLAYER_CAMERA_STEP-th training camera
   and from the held-out ones: whether the players are fitted and do not generalise, or are not fitted.
4. With `--sh-model DIR --dataset D`: what the static layer's degree-1 view-dependent colour buys on a trained
   layered scene. Its static layer is given the fit `stgs train --static-sh 1` runs after stage A (same
   views, same masks, `--sh-iterations`), its dynamic layers are kept as they are, and `stgs eval` scores
   both scenes (`--stride`).
"""

from __future__ import annotations

import argparse
import json
import math
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
from stgs.model.renderer import FrameRenderer
from stgs.synth import SynthConfig, ground_truth_cameras, synthesize, truth_static_layer
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.synth.scene import ProceduralScene


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


FAR_PX = 20
"""--models: pixels closer than this to a player's mask do not count as background far from the players."""
PLAYER_CAMERA_STEP = 4
"""--models: the players are also scored from every this-many-th training camera (what training fitted)."""


def region_psnr(renderer: FrameRenderer, ds, names: list[str], frames: list[int], start: int,
                players: bool = False) -> float:
    """Mean PSNR over `names`' views at `frames` of the GOP: of the background far from the players (outside the masks
    grown by FAR_PX), or with `players` inside the masks. Drawn without the training cameras' colour responses
    (their error, a few hundredths, is small beside the players')."""
    from stgs.metrics import psnr
    from stgs.train.layers import grown_mask

    values = []
    for name in names:
        for i in frames:
            cam = next(c for c in ds.cameras(start + i) if c.name == name)
            mask = ds.mask(start + i, name)
            keep = mask if players else ~grown_mask(mask, mask.shape[1], mask.shape[0], FAR_PX)
            values.append(psnr(renderer.render(i, cam).clamp(0, 1), ds.image(start + i, name), mask=keep))
    return sum(values) / len(values)


def model_rows(dirs: list[Path], dataset: Path, camera: str) -> list[str]:
    from stgs.data import open_dataset
    from stgs.model.store import load_model, load_static

    ds = open_dataset(dataset)
    rows = []
    for d in dirs:
        meta, gops = load_model(d)
        static = load_static(d, meta)
        start = int(meta.extra.get("config", {}).get("start_frame", 0))
        cam = next(c for c in ds.cameras(start) if c.name == camera)
        renderer = FrameRenderer(gops[0], static=static)
        times = []
        for i in range(meta.shape.gop_size + 1):
            t0 = time.perf_counter()
            renderer.render(i % meta.shape.gop_size, cam)
            times.append((time.perf_counter() - t0) * 1e3)

        def live(logits: torch.Tensor) -> int:
            return int((torch.sigmoid(logits.detach()) > 0.02).sum())

        s_total = f"{static.capacity:,} ({live(static.opacity_logit):,})" if static is not None else "-"
        d_live = live(gops[0].opacity_logit)
        held = meta.extra.get("validation_cameras") or [camera]
        trained = (meta.extra.get("train_cameras") or [])[::PLAYER_CAMERA_STEP]
        frames = list(range(0, meta.shape.gop_size, 10))
        far = region_psnr(renderer, ds, held, frames, start)
        players = [region_psnr(renderer, ds, names, frames, start, players=True) if names else math.nan
                   for names in (trained, held)]
        rows.append(f"| {d.name} | {s_total} | {meta.shape.capacity:,} ({d_live:,}) | "
                    f"{statistics.median(times[1:]):.1f} | {far:.2f} | {players[0]:.2f} / {players[1]:.2f} |")
    return rows


def sh_rows(model_dir: Path, dataset: Path, iterations: int, stride: int, work: Path) -> list[str]:
    from stgs.model.store import load_model, load_static, save_model
    from stgs.train.config import LearningRates, TrainConfig
    from stgs.train.images import view_draws
    from stgs.train.layers import fit_view_dependent, moving_pixels
    from stgs.train.run import stage_views
    from stgs.train.trainer import Trainer
    from stgs.tree import CAMERAS, TRAIN_REPORT

    meta, gops = load_model(model_dir)
    static = load_static(model_dir, meta)
    if static is None:
        raise SystemExit(f"{model_dir}: not a layered scene")
    saved = meta.extra["config"]
    cfg = TrainConfig(**(saved | {"lr": LearningRates(**saved["lr"])}))
    trainer = Trainer(dataset, work / "state", cfg, progress=False)
    views, _ = stage_views(trainer, trainer.coarse_frames())
    views.set_masks(moving_pixels(trainer.ds, views, cfg.dynamic_theta))
    start = time.perf_counter()
    draws = view_draws(cfg.seed, "static/sh1", iterations, *views.counts)
    shiny = fit_view_dependent(static, views, draws, cfg.lr.color, cfg.lambda_ssim)
    seconds = time.perf_counter() - start
    views.close()
    scenes = {"sh 0 (as trained)": (model_dir, 0.0), "sh 1": (work / "sh1", seconds)}
    save_model(work / "sh1", gops, meta.fps, meta.extra, static=shiny)
    for name in (CAMERAS, TRAIN_REPORT):
        (work / "sh1" / name).write_bytes((model_dir / name).read_bytes())
    stgs = str(Path(sys.executable).with_name("stgs"))
    rows = []
    for label, (scene, fit_s) in scenes.items():
        out = work / f"ev{len(rows)}"
        subprocess.run([stgs, "eval", str(scene), str(dataset), "--out", str(out), "--stride", str(stride),
                        "--quiet"], check=True, capture_output=True)
        s = json.loads((out / "eval.json").read_text())["streams"]["uncompressed"]
        rows.append(f"| {label} | {fit_s:.0f} | {s['psnr']:.2f} | {s['ssim']:.4f} | "
                    f"{s['psnr_foreground']:.2f} / {s['psnr_background']:.2f} |")
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
    parser.add_argument("--models", help="comma-separated trained scenes: Gaussians per layer and ms/frame")
    parser.add_argument("--camera", default="14", help="--models: the camera to render from")
    parser.add_argument("--sh-model", type=Path, help="a trained layered scene: measure --static-sh 1 on it only")
    parser.add_argument("--dataset", type=Path, help="the dataset --sh-model was trained on")
    parser.add_argument("--sh-iterations", type=int, default=500)
    parser.add_argument("--stride", type=int, default=3, help="--sh-model: evaluate every n-th frame")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}")
    if args.models:
        print("| scene | static Gaussians (live) | dynamic Gaussians per GOP (live) | deform + splat ms/frame | "
              "held-out background far from the players, PSNR | players' PSNR, training / held-out cameras |")
        print("|---|---|---|---|---|---|")
        print("\n".join(model_rows([Path(m) for m in args.models.split(",")], args.dataset, args.camera)))
        return
    if args.sh_model:
        print("| static layer | fit s | held-out PSNR | SSIM | foreground / background PSNR |")
        print("|---|---|---|---|---|")
        with tempfile.TemporaryDirectory() as tmp:
            print("\n".join(sh_rows(args.sh_model, args.dataset, args.sh_iterations, args.stride, Path(tmp))))
        return
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
