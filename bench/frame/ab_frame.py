#!/usr/bin/env python3
"""A/B of the frame path (native deform + splat at 640x360, the splat alone, the deformation alone) between two
source trees.

This machine's speed drifts by up to 20 % over minutes, so kernel changes are
judged by alternating the two builds in one run, never by comparing tables
taken at different times. Each round runs one short subprocess per tree (its
own native build, from its own sources), A then B, then B then A, and so on.

Usage: .venv/bin/python -m bench.frame.ab_frame OLD_TREE NEW_TREE [--rounds 3] [--n 65536] [--frames 25]
       [--model MODEL_DIR]

The scene is a random GOP model of N Gaussians seen by the splatter benchmark's camera, or with
--model a format-1 model dir's GOP 0 at its first camera (frame G/2).

Make OLD_TREE with e.g. `git worktree add /tmp/old <commit>`; both trees use
this virtualenv's packages and build their kernels into the shared cache.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from bench import run_tree

CHILD = r"""
import json, statistics, sys, time
import torch
try:
    from bench.frame.render import bench_camera, random_model
except ImportError:  # a tree from before the benchmarks moved to bench/
    from stgs.benchmarks.render import bench_camera, random_model
try:
    from stgs.model.native_deform import runnable_precisions
except ImportError:  # a tree from before the int16 deformation
    from stgs.model.native_deform import bf16_available
    def runnable_precisions():
        return ["fp32"] + (["bf16"] if bf16_available() else [])
from stgs.model.renderer import FrameRenderer

n, frames, model_dir = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
if model_dir:
    from pathlib import Path
    from bench.frame.culling import first_camera
    from stgs.camera import resize
    from stgs.model.store import load_gop, read_meta
    meta = read_meta(Path(model_dir))
    model, frame = load_gop(Path(model_dir), meta, 0), meta.shape.gop_size // 2
    cam = resize(first_camera(Path(model_dir)), 640, 360)
else:
    model, frame, cam = random_model(n), 30, bench_camera(640, 360)
result = {}
for precision in runnable_precisions():
    renderer = FrameRenderer(model, precision=precision)
    with torch.no_grad():
        g = renderer.gaussians(frame, cam)
        for _ in range(3):
            renderer.render(frame, cam)
        times, splats, deforms = [], [], []
        for _ in range(frames):
            start = time.perf_counter()
            renderer.render(frame, cam)
            mid = time.perf_counter()
            renderer.splat(g, cam)
            end = time.perf_counter()
            renderer.gaussians(frame, cam)
            times.append((mid - start) * 1e3)
            splats.append((end - mid) * 1e3)
            deforms.append((time.perf_counter() - end) * 1e3)
    result[precision] = statistics.median(times)
    result[precision + " deform"] = statistics.median(deforms)
    result.setdefault("splat", statistics.median(splats))
print(json.dumps(result))
"""


def frame_times(tree: Path, n: int, frames: int, model: Path | None) -> dict[str, float]:
    return run_tree(tree, CHILD, [str(n), str(frames), str(model or "")])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--n", type=int, default=65536, help="Gaussians")
    parser.add_argument("--frames", type=int, default=25, help="timed frames per process")
    parser.add_argument("--model", type=Path, help="a format-1 model dir instead of a random model of --n")
    args = parser.parse_args()
    trees = {"old": args.old.resolve(), "new": args.new.resolve()}
    for tree in trees.values():
        if not (tree / "stgs" / "__init__.py").is_file():
            raise SystemExit(f"{tree} is not a streamstgs source tree")
    runs: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
    for r in range(args.rounds):
        for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
            runs[name].append(frame_times(trees[name], args.n, args.frames,
                                      args.model.resolve() if args.model else None))
            print(f"round {r + 1} {name}: " + ", ".join(f"{p} {ms:.1f} ms" for p, ms in runs[name][-1].items()))
    print("\n| what | old ms | new ms | new / old |")
    print("|---|---|---|---|")
    for key in runs["new"][0]:
        if key not in runs["old"][0]:  # a precision only the new tree has
            continue
        old = statistics.median(run[key] for run in runs["old"])
        new = statistics.median(run[key] for run in runs["new"])
        label = ("splat alone (fp32 deformation's Gaussians)" if key == "splat" else
                 f"{key.split()[0]} deformation alone" if key.endswith(" deform") else f"{key} deformation + splat")
        print(f"| {label} | {old:.1f} | {new:.1f} | {new / old:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
