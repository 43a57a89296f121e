"""A/B of the deformation's view culling: Gaussians that cannot reach the image skip the view-dependent decoders.

    python -m bench.frame.culling --model /work/runs/s1 --model /tmp/rt/demo --repeats 30

Per model (format 1, its GOP 0) at its first camera, 640x360: the native fp32 deformation of frame G/2
without a camera (every Gaussian through every decoder) against with one (the culling the player uses),
alternating, medians of `repeats`; then the whole frame both ways (the uncull'd frame applies the guard
band in the splatter instead) and the largest pixel difference between the two images.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from stgs.camera import read_scene_cameras, resize
from stgs.model.native_deform import PackedWeights, deform_native
from stgs.model.renderer import guard_limits, splat
from stgs.model.store import load_gop, read_meta
from stgs.synth import load_ground_truth
from stgs.tree import CAMERAS, GROUND_TRUTH_DIR


def first_camera(model_dir: Path):
    if (model_dir / CAMERAS).is_file():
        return read_scene_cameras(model_dir)[0]
    if (model_dir / GROUND_TRUTH_DIR / CAMERAS).is_file():
        return load_ground_truth(model_dir)[1][0]
    raise SystemExit(f"{model_dir}: no cameras")


def measure(model_dir: Path, repeats: int) -> str:
    meta = read_meta(model_dir)
    model = load_gop(model_dir, meta, 0)
    cam = resize(first_camera(model_dir), 640, 360)
    frame, center, weights = meta.shape.gop_size // 2, cam.center.float(), PackedWeights(model)

    def plain():
        return deform_native(model, frame, center, weights)

    def culled():
        return deform_native(model, frame, center, weights, cam.viewmat, cam.K, cam.width, cam.height,
                             guard=guard_limits(cam))

    times: dict[str, list[float]] = {"plain": [], "culled": [], "plain frame": [], "culled frame": []}
    for _ in range(3):
        plain(), culled()
    for _ in range(repeats):
        for name, fn in (("plain", plain), ("culled", culled)):
            start = time.perf_counter()
            g = fn()
            mid = time.perf_counter()
            splat(g, cam, guarded=name == "culled")
            times[name].append((mid - start) * 1e3)
            times[f"{name} frame"].append((time.perf_counter() - start) * 1e3)
    g_plain, g_culled = plain(), culled()
    kept = int((g_culled.opacities > 0).sum())
    diff = (splat(g_plain, cam) - splat(g_culled, cam, guarded=True)).abs().max().item()
    med = {k: statistics.median(v) for k, v in times.items()}
    return (f"| {model_dir.name} | {meta.shape.capacity:,} | {kept:,} | {med['plain']:.1f} | {med['culled']:.1f} | "
            f"×{med['culled'] / med['plain']:.2f} | {med['plain frame']:.1f} | {med['culled frame']:.1f} | "
            f"{diff:.1e} |")


def table_main(doc: str, header: str, measure: Callable[[Path, int], str]) -> int:
    """The CLI of a per-model table: --model (repeatable) and --repeats, then one row per model."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--model", type=Path, action="append", required=True)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    print(f"{torch.get_num_threads()} threads\n")
    print(header + "\n|" + "---|" * header.count(" | ") + "---|")
    for model in args.model:
        print(measure(model, args.repeats), flush=True)
    return 0


def main() -> int:
    return table_main(__doc__, "| scene | Gaussians | kept by the culling | deform ms, no culling | "
                      "deform ms, culled | ratio | frame ms, no culling | frame ms, culled | max pixel difference |",
                      measure)


if __name__ == "__main__":
    raise SystemExit(main())
