"""A/B of the static layer kept per camera (stgs.render.fixed) against one splat of both layers every frame.

    python -m bench.frame.static_tiles --model /tmp/rt/lay100 --model /tmp/rt/lay46 --frames 30 --rounds 5

Per layered model dir (format 2), GOP 0 at its first camera, 640x360, native fp32 deformation: the frames of
the GOP's first `frames` are drawn from a still camera both ways, alternating A and B in each round so that
the machine's drift hits both alike: "every tile" splats the static layer and the deformed dynamic layer in
one call (the player's path before the kept layer); "kept" draws them with FrameRenderer.draw, which
composites only the tiles the dynamic layer reaches; the frame that keeps the layer (the second one from a
camera, which also renders the static layer alone) is timed on its own. Both images are checked equal,
frame by frame. A
moving camera (a new pose every frame) gets no kept layer and pays the "every tile" cost; its row measures
that the check costs nothing there. Prints Markdown for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import time
from pathlib import Path

import torch

from bench import ms_cell
from bench.frame.culling import first_camera
from stgs.camera import Camera, look_at, resize
from stgs.model.renderer import FrameRenderer
from stgs.model.static import merge
from stgs.model.store import load_gop, load_static, read_meta
from stgs.render.stages import TILE


def every_tile(renderer: FrameRenderer, frame: int, cam: Camera) -> torch.Tensor:
    dynamic = renderer.dynamic_gaussians(frame, cam)
    return renderer.splat(merge(renderer.static_gaussians(cam), dynamic), cam, guarded=True)


def kept(renderer: FrameRenderer, frame: int, cam: Camera) -> torch.Tensor:
    return renderer.draw(renderer.dynamic_gaussians(frame, cam), cam)


def timed(fn) -> tuple[float, torch.Tensor]:
    start = time.perf_counter()
    out = fn()
    return (time.perf_counter() - start) * 1e3, out


def orbit_step(cam: Camera, i: int) -> Camera:
    """cam turned by i small steps about its look-at axis (a new pose every frame)."""
    eye = cam.center.double()
    angle = torch.tensor(0.002 * i, dtype=torch.float64)
    rot = torch.tensor([[torch.cos(angle), 0, torch.sin(angle)], [0, 1, 0], [-torch.sin(angle), 0, torch.cos(angle)]],
                       dtype=torch.float64)
    forward = cam.viewmat[2, :3].double()
    return Camera(cam.name, cam.K, look_at(tuple((rot @ eye).tolist()), tuple((rot @ (eye + forward)).tolist())),
                  cam.width, cam.height)


def measure(model_dir: Path, frames: int, rounds: int, precision: str = "fp32") -> list[str]:
    meta = read_meta(model_dir)
    if meta.static is None:
        raise SystemExit(f"{model_dir} has no static layer (format 1)")
    renderer = FrameRenderer(load_gop(model_dir, meta, 0), static=load_static(model_dir, meta), precision=precision)
    cam = resize(first_camera(model_dir), 640, 360)
    frames = min(frames, meta.shape.gop_size)
    times: dict[str, list[float]] = {"every": [], "kept": [], "deform": [], "moving every": [], "moving": [],
                                     "settle": []}
    reused = []
    with torch.no_grad():
        every_tile(renderer, 0, cam)  # warm
        for r in range(rounds):
            kept(renderer, 0, cam)  # the camera stops: the next frame keeps the static layer
            times["settle"].append(timed(lambda: kept(renderer, 1, cam))[0])
            for name in ("every", "kept") if r % 2 == 0 else ("kept", "every"):
                for i in range(frames):
                    fn = every_tile if name == "every" else kept
                    ms, image = timed(lambda fn=fn, i=i: fn(renderer, i, cam))
                    times[name].append(ms)
                    if name == "kept":
                        reused.append(renderer.static_drawer._kept[1].last_reused_tiles)
                        if not torch.equal(image, every_tile(renderer, i, cam)):
                            raise SystemExit(f"{model_dir.name} frame {i}: the kept layer changed the image")
            draw, name = (kept, "moving") if r % 2 else (every_tile, "moving every")
            for i in range(frames):
                times["deform"].append(timed(lambda i=i: renderer.dynamic_gaussians(i, cam))[0])
                moved = orbit_step(cam, r * frames + i + 1)
                times[name].append(timed(lambda i=i, c=moved, draw=draw: draw(renderer, i, c))[0])
    med = {k: statistics.median(v) for k, v in times.items()}
    tiles = -(-cam.width // TILE) * -(-cam.height // TILE)
    static_n, dynamic_n = meta.static.capacity, meta.shape.capacity
    copied = 100 * statistics.median(reused) / tiles
    return [f"| {model_dir.name} | {static_n:,} + {dynamic_n:,} | {precision} | {copied:.0f} % | "
            f"{ms_cell(med['deform'])} | {ms_cell(med['every'])} | {ms_cell(med['kept'])} | "
            f"{med['kept'] / med['every']:.2f} | "
            f"{ms_cell(med['settle'])} | {ms_cell(med['moving every'])} | {ms_cell(med['moving'])} |"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="a layered model dir")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--precisions", default="fp32", help="deformation precisions, e.g. fp32,bf16")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"<!-- python -m bench.frame.static_tiles, {platform.processor() or platform.machine()}, "
          f"torch threads {torch.get_num_threads()}, commit {commit} -->")
    print("| scene | Gaussians static + dynamic | deformation | tiles copied | deform ms | "
          "deform + splat ms, every tile | deform + splat ms, static layer kept | kept / every | "
          "frame that keeps the layer, ms | moving camera ms, before | moving camera ms, now |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for model in args.model:
        for precision in args.precisions.split(","):
            print("\n".join(measure(model, args.frames, args.rounds, precision)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
