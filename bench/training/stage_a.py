"""Stage A alone (the static layer of `stgs train --layers layered`): its wall time and how well the static layer
draws the background, per setting and seed (`python -m bench.training.stage_a`, prints Markdown rows for
docs/BENCHMARKS.md).

Each row trains stage A (the budget's layered config, `cpu` by default, with `--set`'s overrides, `--no-aux`, one
GOP unless `max_gops` is set, the `--holdout` cameras left out) in a fresh folder and draws the static layer alone
at every 6th frame of the trained span: from the held-out cameras, and from every 6th training camera through its
learnt colour response (what training fitted). PSNR over the pixels outside the dataset's foreground masks grown as
stgs.train.layers.grown_mask grows them, the pixels stage A fits. The background is most of a layered run's held-out
error (nine-tenths of Panoptic's pixels, about two-thirds of the squared error), and this measures it in half a
run's time.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import tempfile
import time
from pathlib import Path

import torch

from stgs.data import open_dataset
from stgs.train.config import budget
from stgs.train.layers import MASK_DILATE_PX, static_background_psnr
from stgs.train.run import base_stage
from stgs.train.trainer import Trainer

FRAME_STEP = 6
"""Every this many frames of the GOP are drawn, and every this many training cameras."""
LR_PREFIX = "lr."
"""A `--set` key with this prefix names a learning rate (LearningRates), not a TrainConfig field."""


def parse_settings(text: str) -> dict:
    """'coarse_low_res=0.6,lr.camera_colour=3e-4' -> TrainConfig overrides, `lr.NAME` for a learning rate (numbers
    as int or float)."""
    out = {}
    for part in filter(None, text.split(",")):
        key, _, value = part.partition("=")
        out[key.strip()] = float(value) if "." in value or "e" in value else int(value)
    return out


def row(dataset: Path, holdout: list[str], settings: dict, seed: int, work: Path, budget_name: str = "cpu") -> str:
    """One table row: stage A trained in `work` with `settings` over the budget's layered config (`lr.NAME` keys
    set Adam's rates, as `stgs train --lr NAME=RATE` does)."""
    rates = {k.removeprefix(LR_PREFIX): v for k, v in settings.items() if k.startswith(LR_PREFIX)}
    fields = {k: v for k, v in settings.items() if not k.startswith(LR_PREFIX)}
    cfg = budget(budget_name, **({"layers": "layered", "holdout": holdout, "max_gops": 1, "aux": False,
                                  "seed": seed} | fields))
    cfg = dataclasses.replace(cfg, lr=cfg.lr.with_rates(rates))
    trainer = Trainer(dataset, work, cfg, progress=False)
    trainer.prepare_output()
    start = time.perf_counter()
    base = base_stage(trainer)
    seconds = time.perf_counter() - start
    ds = open_dataset(dataset)
    frames = list(range(cfg.start_frame, cfg.start_frame + trainer.num_gops * cfg.gop_size, FRAME_STEP))
    trained = trainer.train_names[::FRAME_STEP]
    held_out = static_background_psnr(base.static, ds, trainer.val_names, frames, MASK_DILATE_PX)
    fitted = static_background_psnr(base.static, ds, trained, frames, MASK_DILATE_PX, base.colour,
                                   [trainer.train_names.index(n) for n in trained])
    label = ", ".join(f"{k} {v:g}" for k, v in settings.items()) or "the budget's"
    return f"| {label} | {seed} | {seconds:.0f} | {held_out:.2f} | {fitted:.2f} |"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--holdout", default="1,14,27")
    p.add_argument("--set", action="append", default=[], metavar="K=V,...",
                   help="one row's TrainConfig overrides, lr.NAME=RATE for a learning rate (repeat for more "
                        "rows; none: the budget's stage A)")
    p.add_argument("--seeds", default="0")
    p.add_argument("--budget", default="cpu")
    args = p.parse_args()
    settings = [parse_settings(s) for s in args.set] or [{}]
    print(f"machine: {platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}")
    print("| stage A | seed | s | held-out background PSNR | training cameras' background PSNR |")
    print("|---|---|---|---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        for setting in settings:
            with tempfile.TemporaryDirectory() as work:
                print(row(args.dataset, args.holdout.split(","), setting, seed, Path(work) / "run", args.budget),
                      flush=True)


if __name__ == "__main__":
    main()
