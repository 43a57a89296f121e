"""Subcommands that make and measure a model dir: `stgs synth`, `stgs train`, `stgs eval`."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from stgs.cli.args import (
    UsageError,
    add_ray,
    byte_size,
    effect_list,
    name_list,
    name_number,
    positive_float,
    positive_int,
    positive_seconds,
)
from stgs.cli.config_flags import ConfigFlag, add_config_flags, config_values
from stgs.cli.interop import add_static_import, describe_import, static_import_overrides


def synth_flags() -> tuple[ConfigFlag, ...]:
    """The SynthConfig fields `stgs synth` sets; their defaults are the preset's."""
    preset = "the preset's"
    return (
        ConfigFlag("grid_side", type=positive_int, metavar="S", default_note=preset),
        ConfigFlag("num_gops", "--gops", type=positive_int, default_note=preset),
        ConfigFlag("gop_size", type=positive_int, default_note=preset),
        ConfigFlag("width", type=positive_int, default_note=preset),
        ConfigFlag("height", type=positive_int, default_note=preset),
        ConfigFlag("num_cameras", "--cameras", type=positive_int, default_note=preset),
        ConfigFlag("fit_steps", default_note=preset),
        ConfigFlag("feature_smoothness", default_note=preset),
        ConfigFlag("seed", default_note=preset),
        ConfigFlag("effects", type=effect_list, metavar="EFFECTS", default_note=preset),
        ConfigFlag("static_grid_side", type=positive_int, default_note=preset),
        ConfigFlag("fold", on=True),
    )


SECONDS = (ConfigFlag("num_gops", "--seconds"),)
"""--seconds sets the scene's length in place of --gops (named in the help texts)."""


def add_synth(sub: argparse._SubParsersAction) -> None:
    from stgs.synth import PRESETS
    from stgs.synth.config import SynthConfig

    p = sub.add_parser("synth", help="generate a synthetic dynamic scene: ground truth + model dir",
                       description="Generate a procedural dynamic scene, render its ground-truth "
                       "multi-view images and fit a StreamSTGS model dir to it in parameter space.")
    p.add_argument("out", type=Path, help="output model dir (replaced if it is a model dir)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="small",
                   help="base configuration (default: small)")
    p.add_argument("--config", type=Path, help="TOML file overriding SynthConfig fields")
    add_config_flags(p, SynthConfig, synth_flags(), among=SECONDS)
    p.add_argument("--seconds", type=positive_seconds,
                   help="the capture's length instead of --gops: as many GOPs as it takes at the scene's fps")
    add_static_import(p, train=False)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_synth)


def synth_config_from_args(args: argparse.Namespace):
    from stgs.synth import PRESETS, config_from_toml

    cfg = PRESETS[args.preset]
    if args.config:
        cfg = config_from_toml(args.config, cfg)
    cfg = dataclasses.replace(cfg, **config_values(args, synth_flags()))
    if args.static_from is not None:
        from stgs.interop.static import read_transform

        matrix = None if args.static_transform is None else read_transform(args.static_transform).reshape(-1)
        cfg = dataclasses.replace(cfg, static_from=str(args.static_from), effects=tuple(dict.fromkeys(
            (*cfg.effects, "static_background"))), static_transform=None if matrix is None else tuple(matrix.tolist()))
    elif args.static_transform is not None:
        raise UsageError("--static-transform needs --static-from")
    if args.seconds is not None:
        if args.num_gops is not None:
            raise UsageError("--seconds and --gops both set the scene's length: give one")
        cfg = dataclasses.replace(cfg, num_gops=cfg.gops_for_seconds(args.seconds))
    cfg.validate()
    return cfg


def run_synth(args: argparse.Namespace) -> int:
    cfg = synth_config_from_args(args)  # a mistake is reported before the generator loads
    from stgs.synth import synthesize

    report = synthesize(cfg, args.out, progress=not args.quiet)
    layered = "static_background" in cfg.effects and not cfg.fold
    static = f" + a static layer of {cfg.static_grid_side ** 2}" if layered else ""
    if cfg.static_from is not None:
        static = f" + the static layer of {cfg.static_from}"
    if cfg.fold:
        static = f" (backdrop of {cfg.static_grid_side ** 2} folded into every GOP)"
    print(f"wrote {args.out}: {cfg.grid_side ** 2} Gaussians{static}, {cfg.num_gops} GOPs x "
          f"{cfg.gop_size} frames ({cfg.num_gops * cfg.gop_size / cfg.fps:g} s at {cfg.fps:g} fps), "
          f"effects {','.join(cfg.effects) or 'none'}")
    print(f"fidelity of the model vs ground truth: {report.fidelity_psnr:.2f} dB PSNR "
          f"over {report.fidelity_views} views")
    return 0


def add_train(sub: argparse._SubParsersAction) -> None:
    from stgs.data import KINDS
    from stgs.train.config import BUDGETS, LearningRates, TrainConfig

    p = sub.add_parser("train", help="train a StreamSTGS model dir from multi-view video (CPU)",
                       description="Per-GOP StreamSTGS training: triangulated initial points, a coarse canonical "
                       "stage, then per GOP canonical Gaussians + temporal features + deformation field with the "
                       "paper's losses, relocation and pruning. Writes a model dir `stgs pack` accepts.")
    p.add_argument("dataset", type=Path, help="Panoptic folder (train_meta.json), N3DV folder "
                   "(poses_bounds.npy + cam*.mp4), a stgs synth model dir, a nerfstudio transforms.json or a COLMAP "
                   "capture (docs/CAPTURE.md; `stgs inspect` shows what it holds)")
    p.add_argument("out", type=Path, help="output model dir")
    p.add_argument("--budget", choices=sorted(BUDGETS), default="quick",
                   help="quick (CI and smoke runs), cpu (a real capture's GOP on a few cores), paper (the paper's "
                   "sizes, for a bigger machine); sizes and times: docs/TRAINING.md, 'Budgets'")
    p.add_argument("--kind", choices=["auto", *KINDS], default="auto", help="dataset layout (default: auto)")
    add_config_flags(p, TrainConfig, train_flags())
    p.add_argument("--position-lr", type=float,
                   help="initial position learning rate × the scene extent (decays 100× over a stage; "
                   "default: the budget's); the same as --lr position=RATE")
    rates = ", ".join(f.name for f in dataclasses.fields(LearningRates))
    p.add_argument("--lr", action="append", metavar="NAME=RATE",
                   help=f"an Adam learning rate, repeatable: {rates} (position × the scene extent; a decaying rate "
                   "set without its _final keeps its decay; default: the budget's)")
    add_static_import(p, train=True)
    add_ray(p, "the base stage, then one task per GOP,")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from its checkpoints")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_train)


def budget_default(field: str) -> str | None:
    """A TrainConfig field's default as the command line says it: its value where every budget (and every
    budget's layered variant) agrees, else that the budget sets it."""
    from stgs.train.config import BUDGETS, LAYERED

    values = {repr(getattr(cfg, field)) for cfg in BUDGETS.values()}
    values |= {repr(layered[field]) for layered in LAYERED.values() if field in layered}
    if len(values) == 1:
        value = getattr(next(iter(BUDGETS.values())), field)
        return None if value is None else str(value)
    return "the budget's; docs/TRAINING.md, 'Budgets'"


def train_flags() -> tuple[ConfigFlag, ...]:
    """The TrainConfig fields `stgs train` sets; the switches that turn a component off come in the order the
    training benchmark names them (bench/training/train.py)."""
    from stgs.train.config import LAYERS

    def flag(field: str, option: str | None = None, **kw) -> ConfigFlag:
        if "default_note" not in kw and not kw.get("off"):
            kw["default_note"] = budget_default(field)
        return ConfigFlag(field, option, **kw)

    return (
        flag("holdout", type=name_list, metavar="CAMERAS"),
        flag("fps", type=positive_float),
        flag("max_gops", "--gops", type=positive_int),
        flag("gop_size", type=positive_int),
        flag("start_frame", type=int),
        flag("grid_side", type=positive_int),
        flag("layers", choices=LAYERS),
        flag("static_grid_side", type=positive_int),
        flag("static_drop_rate", type=float),
        flag("static_drop_until", type=float),
        flag("static_sh_degree", "--static-sh", type=int, choices=[0, 1]),
        flag("static_sh_iterations", type=int),
        flag("dynamic_warmup", type=float),
        flag("iterations", type=positive_int),
        flag("coarse_iterations", type=int),
        flag("coarse_low_res", type=float),
        flag("gop_low_res", type=float),
        flag("scale", type=float),
        flag("window", type=positive_int),
        flag("background_share", type=float),
        flag("init_frames", type=positive_int),
        flag("aux", "--no-aux", off=True),
        flag("dynamic", "--no-dynamic-density", off=True),
        flag("temporal_weight", "--no-temporal-reg", off=True, off_value=0.0),
        flag("relocate", "--no-relocate", off=True),
        flag("migrate", "--no-migrate", off=True),
        flag("hull_seeds", "--no-hull-seeds", off=True),
        flag("camera_colour", "--no-camera-colour", off=True),
        flag("static_triangulation", "--no-static-triangulation", off=True),
        flag("seed", type=int),
        flag("threads", type=positive_int),
        flag("max_memory", type=byte_size, metavar="SIZE"),
        flag("static_frames", type=positive_int),
    )


def train_overrides(args: argparse.Namespace) -> dict:
    """TrainConfig fields the command line sets (the rest come from the budget)."""
    from stgs.train.config import BUDGETS

    overrides = config_values(args, train_flags())
    overrides |= static_import_overrides(args)
    rates = dict(name_number(text, "--lr") for text in args.lr or ())
    if args.position_lr is not None:
        if "position" in rates:
            raise UsageError("--position-lr and --lr position=... both set the position learning rate")
        rates["position"] = args.position_lr
    if rates:  # names: LearningRates.with_rates; values: TrainConfig.validate
        overrides["lr"] = BUDGETS[args.budget].lr.with_rates(rates)
    return overrides


def gop_sizes_covering(frames: int, gop_size: int, most: int = 2) -> list[int]:
    """Up to `most` GOP sizes from half to twice `gop_size` that divide `frames` exactly, the closest first."""
    sizes = [g for g in range(max(2, gop_size // 2), 2 * gop_size + 1) if frames % g == 0]
    return sorted(sizes, key=lambda g: (abs(g - gop_size), -g))[:most]  # a tie: the longer GOP, fewer keyframes


def run_train(args: argparse.Namespace) -> int:
    from stgs.train import budget

    cfg = budget(args.budget, **train_overrides(args))  # a mistake is reported before the trainer loads
    from stgs.data import open_dataset
    from stgs.train import train

    num_frames = open_dataset(args.dataset, args.kind, fps=cfg.fps).num_frames
    if num_frames - cfg.start_frame == 1 and args.layers is None:
        cfg = budget(args.budget, **train_overrides(args) | {"layers": "still"})
        print("stgs: note: the capture has one frame: training a still scene (--layers still)", file=sys.stderr)
    tail = None if cfg.layers == "still" else cfg.untrained_tail(num_frames)
    if tail is not None:
        usable = num_frames - cfg.start_frame
        sizes = " or ".join(f"--gop-size {g}" for g in gop_sizes_covering(usable, cfg.gop_size))
        hint = f"; {sizes} would cover all {usable}" if sizes else ""
        print(f"stgs: note: frames {tail[0]}-{tail[1]} do not fill a GOP of {cfg.gop_size} and are not trained{hint}",
              file=sys.stderr)
    report = train(args.dataset, args.out, cfg, progress=not args.quiet, resume=args.resume, kind=args.kind,
                   ray=args.ray, retries=args.ray_retries)
    for g in report["gops"]:
        val = f", validation {g['val_psnr']:.2f} dB" if g["val_psnr"] is not None else ""
        print(f"GOP {g['gop']}: {g['iterations']} iterations in {g['seconds']:.0f} s, train {g['train_psnr']:.2f} dB"
              f"{val}, {g['relocated']} relocated, {g['pruned']} pruned")
    if "static_capacity" in report and not report.get("still"):
        print(f"static layer: {report['static_capacity']} Gaussians in {report['static_seconds']:.0f} s "
              f"(moving pixels from {report['moving_mask_source']}; {report['migrated']} Gaussians migrated to the "
              "dynamic layers)")
    if "static_import" in report:
        print(describe_import(report["static_import"]))
    if report.get("still"):
        val = f", validation {report['val_psnr']:.2f} dB" if report.get("val_psnr") is not None else ""
        print(f"wrote {args.out}: a still scene of {report['static_capacity']} Gaussians (train "
              f"{report['train_psnr']:.2f} dB{val}, {report['static_seconds']:.0f} s)")
        return 0
    print(f"wrote {args.out} ({report['capacity']} Gaussians per GOP, {len(report['gops'])} GOP(s))")
    return 0


def add_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="PSNR/SSIM of a model dir (and its packaged stream) on held-out cameras",
                       description="Render the validation cameras of every GOP from the uncompressed model and, "
                       "with --dash, from every Representation of its DASH tree; compare with the dataset.")
    p.add_argument("model_dir", type=Path, help="model dir (stgs train output)")
    p.add_argument("dataset", type=Path, help="the dataset it was trained on")
    p.add_argument("--dash", type=Path, help="the model's packaged tree (stgs pack output) to evaluate per QP")
    p.add_argument("--holdout", type=name_list,
                   help="validation cameras (default: those the model was trained without)")
    p.add_argument("--stride", type=positive_int, default=1, help="evaluate every n-th frame (default: 1)")
    p.add_argument("--out", type=Path, help="where eval.json and eval_grid.png go (default: MODEL_DIR)")
    p.add_argument("--lpips", choices=["alex", "vgg", "off"], default="alex",
                   help="LPIPS network, computed only where torchvision's cache ($TORCH_HOME/hub/checkpoints) "
                   "already holds its ImageNet backbone; nothing is downloaded (default: alex)")
    p.add_argument("--max-memory", type=byte_size, metavar="SIZE",
                   help="decoded held-out views held at once, e.g. 512M (default: the machine's RAM / 16, at most 1G)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_eval)


def run_eval(args: argparse.Namespace) -> int:
    from stgs.evaluate import evaluate

    result = evaluate(args.model_dir, args.dataset, args.out or args.model_dir, args.dash, args.holdout,
                      args.stride, progress=not args.quiet, lpips_net=None if args.lpips == "off" else args.lpips,
                      max_memory=args.max_memory)
    for name, stream in result["streams"].items():
        regions = (f" (foreground {stream['psnr_foreground']:.2f} dB, background {stream['psnr_background']:.2f} dB)"
                   if "psnr_foreground" in stream and "psnr_background" in stream else "")
        lpips = f", LPIPS ({args.lpips}) {stream['lpips']:.4f}" if "lpips" in stream else ""
        print(f"{name}: PSNR {stream['psnr']:.2f} dB{regions}, SSIM {stream['ssim']:.4f}{lpips} over "
              f"{len(stream['gops'])} GOP(s)")
    if result["lpips"] and not result["lpips"]["computed"]:
        print(f"LPIPS not computed: {result['lpips']['reason']}")
    print(f"wrote {(args.out or args.model_dir) / 'eval.json'}")
    return 0
