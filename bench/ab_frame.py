#!/usr/bin/env python3
"""A/B of the frame path (native deform + splat at 640x360) between two source trees.

This machine's speed drifts by up to 20 % over minutes, so kernel changes are
judged by alternating the two builds in one run, never by comparing tables
taken at different times. Each round runs one short subprocess per tree (its
own native build, from its own sources), A then B, then B then A, and so on.

Usage: .venv/bin/python -m bench.ab_frame OLD_TREE NEW_TREE [--rounds 3] [--n 65536] [--frames 25]

Make OLD_TREE with e.g. `git worktree add /tmp/old <commit>`; both trees use
this virtualenv's packages and build their kernels into the shared cache.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, statistics, sys, time
import torch
try:
    from bench.render import bench_camera, random_model
except ImportError:  # a tree from before the benchmarks moved to bench/
    from stgs.benchmarks.render import bench_camera, random_model
from stgs.model.native_deform import bf16_available
from stgs.model.view import FrameRenderer

n, frames = int(sys.argv[1]), int(sys.argv[2])
cam = bench_camera(640, 360)
model = random_model(n)
result = {}
for precision in ["fp32"] + (["bf16"] if bf16_available() else []):
    renderer = FrameRenderer(model, precision=precision)
    with torch.no_grad():
        for _ in range(3):
            renderer.render(30, cam)
        times = []
        for _ in range(frames):
            start = time.perf_counter()
            renderer.render(30, cam)
            times.append((time.perf_counter() - start) * 1e3)
    result[precision] = statistics.median(times)
print(json.dumps(result))
"""


def run_tree(tree: Path, n: int, frames: int) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(tree))
    proc = subprocess.run([sys.executable, "-c", CHILD, str(n), str(frames)], cwd=tree, env=env,
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else 'failed'}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--n", type=int, default=65536, help="Gaussians")
    parser.add_argument("--frames", type=int, default=25, help="timed frames per process")
    args = parser.parse_args()
    trees = {"old": args.old.resolve(), "new": args.new.resolve()}
    for tree in trees.values():
        if not (tree / "stgs" / "__init__.py").is_file():
            raise SystemExit(f"{tree} is not a streamstgs source tree")
    runs: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
    for r in range(args.rounds):
        for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
            runs[name].append(run_tree(trees[name], args.n, args.frames))
            print(f"round {r + 1} {name}: " + ", ".join(f"{p} {ms:.1f} ms" for p, ms in runs[name][-1].items()))
    print("\n| deformation | old deform + splat ms | new deform + splat ms | new / old |")
    print("|---|---|---|---|")
    for precision in runs["new"][0]:
        old = statistics.median(run[precision] for run in runs["old"])
        new = statistics.median(run[precision] for run in runs["new"])
        print(f"| {precision} | {old:.1f} | {new:.1f} | {new / old:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
