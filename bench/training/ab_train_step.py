#!/usr/bin/env python3
"""A/B of a training step on Panoptic between two source trees: stage A's step (the static layer, 25,600
Gaussians), stage B's (the dynamic layer, 9,216, over the kept static layer) and format 1's GOP step (16,384),
the `cpu` budget's sizes at 640x360 without the auxiliary pass.

Usage: .venv/bin/python -m bench.training.ab_train_step OLD_TREE NEW_TREE --dataset ../shared/data/panoptic-basketball
       [--rounds 2] [--steps 60]

Each round runs one subprocess per tree and kind of run (its own native build, from its own sources), A then B,
then B then A (the machine's drift hits both alike). A subprocess fits a 30-iteration base stage (its step
times do not depend on how well it is fitted), loads every 6th frame of GOP 0, then times `--steps` steps of
each stage after 20 untimed ones: the loss as the trainer forms it, its backward pass and Adam's step; medians.
Make OLD_TREE with e.g. `git worktree add /tmp/old <commit>`; both trees use this virtualenv's packages.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from bench import run_tree

CHILD = r"""
import json, statistics, sys, tempfile, time
from pathlib import Path
import torch
from stgs.model.gop import GOPModel
from stgs.model.renderer import splat, static_backdrops
from stgs.train import losses
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.config import budget
from stgs.train.dynamic import gop_dynamic_masks
from stgs.train.layers import moving_pixels
from stgs.train.objective import canonical_regularisers, drop_gaussians
from stgs.train.ops import Optimizer
from stgs.train.run import base_stage, stage_views
from stgs.picks import spread
from stgs.train.seeding import init_canonical, initial_points
from stgs.train.trainer import Trainer

dataset, layers, steps = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
cfg = budget("cpu", layers=layers, holdout=["1", "14", "27"], max_gops=1, aux=False, seed=0, coarse_iterations=30)
trainer = Trainer(dataset, Path(tempfile.mkdtemp()) / "run", cfg, progress=False)
trainer.prepare_output()
base = base_stage(trainer)


def median_ms(step):
    for _ in range(20):
        step()
    times = []
    for _ in range(steps):
        begin = time.perf_counter()
        step()
        times.append(time.perf_counter() - begin)
    return 1000 * statistics.median(times)


def optimise(opt, loss):
    opt.opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.opt.step()


result = {}
frames = trainer.gop_frames(0)[::6]
views, _ = stage_views(trainer, frames)
if layers == "layered":
    views.set_masks(moving_pixels(trainer.ds, views, cfg.dynamic_theta))
    static = GOPModel(trainer.static_shape)
    colour = CameraColour(len(views.cameras))
    opt = Optimizer(static, cfg, trainer.extent, None, canonical_only=True, colour=colour)
    init = initial_points(trainer.ds, trainer.train_names, spread(views.frames, cfg.init_frames),
                          static.shape.capacity, trainer.gen, cfg.init_points, cfg.background_share,
                          region="background")
    init_canonical(static, init)

    def stage_a():
        f = int(torch.randint(len(views.frames), (1,), generator=trainer.gen))
        c = int(torch.randint(len(views.cameras), (1,), generator=trainer.gen))
        g = static.canonical()
        img = as_recorded(colour, splat(drop_gaussians(g, cfg.static_drop_rate, trainer.gen), views.cameras[c]), c)
        loss = losses.photometric(img, views.target(f, c), cfg.lambda_ssim, ~views.dynamic_pixels(f, c))
        optimise(opt, loss + canonical_regularisers(cfg, static, g.opacities))

    result["stage A step"] = median_ms(stage_a)
else:
    masks = gop_dynamic_masks(views, cfg.dynamic_frames, cfg.dynamic_theta).numpy()
    views.set_masks(lambda frame, c: masks[c])
trainer.seed_stage("gop0")
model = trainer.start_model(0, base.coarse)
backdrops = static_backdrops(trainer.static, views.cameras) if trainer.static is not None else None
opt = Optimizer(model, cfg, trainer.extent, None)
key = "stage B step" if layers == "layered" else "format 1 GOP step"
result[key] = median_ms(lambda: optimise(opt, trainer.gop_loss(model, None, views.sample(0, 0), backdrops).loss))
print(json.dumps(result))
"""

KINDS = ("layered", "single")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--steps", type=int, default=60)
    args = parser.parse_args()
    trees = {"old": args.old.resolve(), "new": args.new.resolve()}
    runs: dict[str, dict[str, list[float]]] = {"old": {}, "new": {}}
    for r in range(args.rounds):
        for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
            for kind in KINDS:
                result = run_tree(trees[name], CHILD, [str(args.dataset.resolve()), kind, str(args.steps)])
                for what, ms in result.items():
                    runs[name].setdefault(what, []).append(ms)
                print(f"round {r + 1} {name} {kind}: " + ", ".join(f"{w} {ms:.1f} ms" for w, ms in result.items()),
                      flush=True)
    print("\n| step | old ms (each round) | new ms (each round) | new / old (medians) |")
    print("|---|---|---|---|")
    for what, new in runs["new"].items():
        old = runs["old"][what]
        print(f"| {what} | {', '.join(f'{v:.0f}' for v in old)} | {', '.join(f'{v:.0f}' for v in new)} | "
              f"{statistics.median(new) / statistics.median(old):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
