"""Accuracy vs time of the player's knobs: QP, deformation precision, resolution, ring length, thread budget.

    python -m bench.playback.knobs --model /work/runs/s1 --work /tmp/rt --seconds 8

One scene (looped and packed as bench.playback.realtime does), played by `stgs play` in its own process once per knob
setting, every frame rendered as fast as it can (not --realtime, so each setting's full cost shows) at the
scene's first camera. Per setting: per-frame decode + dequantise, wait, deform and splat (medians), frames per
second, the ring's memory, and the PSNR of the streamed frames (in the setting's precision) against the
uncompressed model's (float32) at the same camera and size (first, middle and last frame of each of the
scene's own GOPs; streamed frames equal the whole-GOP decode bit for bit, so the comparison decodes each GOP
whole).
"""

from __future__ import annotations

import argparse
import asyncio
import platform
import statistics
from pathlib import Path

import torch

from bench.playback.playlog_stats import frame_stats
from bench.playback.realtime import loop_model, play_process
from stgs.camera import Camera, read_scene_cameras, resize
from stgs.metrics import psnr
from stgs.model.native_deform import runnable_precisions
from stgs.model.renderer import FrameRenderer
from stgs.model.store import load_model, read_meta
from stgs.packaged import packaged_gops
from stgs.packager import PackConfig, pack
from stgs.server.app import loopback
from stgs.tree import MANIFEST, rep_id

BASE = {"qp": 24, "precision": "fp32", "size": "640x360", "ring": 8, "render_threads": None}
VARIANTS = [{}, {"qp": 16}, {"qp": 32}, {"precision": "bf16"}, {"precision": "int16"}, {"size": "320x180"},
            {"size": "1280x720"},
            {"ring": 4}, {"ring": 16}, {"render_threads": 1}]


def streamed_psnr(model_dir: Path, dash: Path, qp: int, camera: Camera, gops: int, precision: str = "fp32") -> float:
    """Mean PSNR of the first, middle and last frame of the scene's first `gops` GOPs, streamed at `qp`
    (decoded whole: bit-exact with the stream) and deformed in `precision`, against the uncompressed model
    deformed in float32, at `camera`."""
    meta, models = load_model(model_dir)
    streamed_gop = packaged_gops(dash)[rep_id(qp)]
    values = []
    for k in range(min(gops, meta.num_gops)):
        streamed, local = FrameRenderer(streamed_gop(k), precision=precision), FrameRenderer(models[k])
        for i in sorted({0, meta.shape.gop_size // 2, meta.shape.gop_size - 1}):
            values.append(psnr(streamed.render(i, camera).clamp(0, 1), local.render(i, camera).clamp(0, 1)))
    return statistics.mean(values)


def setting_args(s: dict, camera: str) -> list[str]:
    args = ["--camera", camera, "--size", s["size"], "--qp", str(s["qp"]), "--precision", s["precision"],
            "--ring-frames", str(s["ring"])]
    return args + (["--render-threads", str(s["render_threads"])] if s["render_threads"] else [])


def label(variant: dict) -> str:
    return "baseline" if not variant else ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in variant.items())


async def measure(model: Path, work: Path, seconds: float) -> list[str]:
    name = model.resolve().name
    looped = loop_model(model, work / f"{name}-looped", seconds)
    dash = work / f"{name}-dash"
    qps = sorted({v.get("qp", BASE["qp"]) for v in VARIANTS})
    pack(looped, dash, PackConfig(ladder="fixed", qps=tuple(qps), resume=True), progress=False)
    cameras = read_scene_cameras(dash)
    n = read_meta(looped).shape.capacity
    rows = []
    async with loopback(dash) as base:
        url = base + MANIFEST
        await play_process(url, work / "warmup.json", ["--camera", cameras[0].name, "--duration", "1"])
        runnable = runnable_precisions()
        for variant in VARIANTS:
            s = {**BASE, **variant}
            if s["precision"] not in runnable:
                rows.append(f"| {label(variant)} | {s['precision']} cannot run on this CPU: not run | | | | | | |")
                continue
            log = await play_process(url, work / f"knob-{name}-{label(variant).replace(' ', '_')}.json",
                                     setting_args(s, cameras[0].name))
            stats = frame_stats(log)
            width, height = (int(v) for v in s["size"].split("x"))
            camera = resize(cameras[0], width, height)
            quality = await asyncio.to_thread(streamed_psnr, model, dash, s["qp"], camera, 2, s["precision"])
            ring_mb = s["ring"] * n * 16 * 4 / 2**20
            frame_ms = stats["render"][0]
            rows.append(f"| {label(variant)} | {stats['decode'][0]:.1f} | {stats['wait'][0]:.1f} | "
                        f"{stats['deform'][0]:.1f} | {stats['splat'][0]:.1f} | **{frame_ms:.1f}** | "
                        f"{1e3 / frame_ms:.1f} | {ring_mb:.1f} | {quality:.2f} |")
            print(rows[-1], flush=True)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--seconds", type=float, default=8.0)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    rows = asyncio.run(measure(args.model, args.work, args.seconds))
    print(f"\nMachine: {platform.machine()}, {torch.get_num_threads()} torch threads; baseline: "
          f"{', '.join(f'{k} {v}' for k, v in BASE.items())}\n")
    print("| setting | decode + dequantise ms | wait ms | deform ms | splat ms | frame ms (render thread) | fps | "
          "ring MB | PSNR vs uncompressed (dB) |\n|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
