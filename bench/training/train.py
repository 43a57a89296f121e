"""Training accuracy vs time from finished `stgs train` runs (`stgs bench train --runs DIR,DIR`).

Reads each model dir's train_report.json (and the eval.json `stgs eval` wrote
there, when present) and prints Markdown: validation PSNR/SSIM against
training seconds per run, the final numbers per GOP, and the evaluation per
stream (uncompressed and each packaged QP). Plots the curves (matplotlib PNG).
Training itself is not run here: a `cpu`-budget GOP takes most of an hour.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from stgs.cli.model import train_flags
from stgs.errors import StgsError
from stgs.fsio import save_figure
from stgs.train.config import BUDGETS
from stgs.tree import MODEL_META, TRAIN_REPORT


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise StgsError(f"{path}: cannot read ({exc})") from None


ABSENT_MEANS_OFF = {"camera_colour": ("single", "layered"), "hull_seeds": ("layered",),
                    "static_triangulation": ("layered",)}
"""Components added after runs were first recorded, and the layers that have them: a run of those layers whose
config lacks the key trained without the component."""


def switched_off(config: dict) -> list[str]:
    """The ablation flags of the components a run's config (model.json's `extra.config`) trained without."""
    layers = config.get("layers", "single")  # runs from before layered training were single-layer
    switches = {spec.field: spec.option for spec in train_flags() if spec.off}
    return [flag for key, flag in switches.items()
            if (key in config and not config[key]) or (key not in config and layers in ABSENT_MEANS_OFF.get(key, ()))]


def run_label(model_dir: Path) -> str:
    """'all components' or the ablation switches the run was trained with, and its capacity, initial-point frames,
    learning rates and seed when they are not the budget's."""
    config = _read_json(model_dir / MODEL_META).get("extra", {}).get("config", {})
    off = switched_off(config)
    label = f"{config.get('budget', '?')}: " + (" ".join(off) if off else "all components")
    default, side = BUDGETS.get(config.get("budget")), config.get("grid_side")
    if default is not None and isinstance(side, int) and side != default.grid_side:
        label += f", {side * side:,} Gaussians"
    frames = config.get("init_frames", 1)  # runs from before the setting triangulated their first frame only
    if default is not None and isinstance(frames, int) and frames != default.init_frames:
        label += f", init frames {frames}"
    rates = config.get("lr") if isinstance(config.get("lr"), dict) else {}
    for name, rate in rates.items():  # a final rate follows its initial one unless set apart
        budget_rate = getattr(default.lr, name, None) if default is not None else None
        if not name.endswith("_final") and isinstance(rate, float) and budget_rate is not None and rate != budget_rate:
            label += f", {name} lr {rate:g}"
    seed = config.get("seed", 0)
    if default is not None and isinstance(seed, int) and seed != default.seed:
        label += f", seed {seed}"
    return label


def distinct_labels(model_dirs: list[Path], labels: list[str]) -> list[str]:
    """Runs whose settings read the same (e.g. one command on two versions of the code) are told apart by
    their folder name."""
    return [f"{label} ({d.name})" if labels.count(label) > 1 else label
            for d, label in zip(model_dirs, labels, strict=True)]


def curve_rows(label: str, report: dict) -> list[str]:
    rows = []
    for gop in report["gops"]:
        for point in gop["curve"]:
            psnr, ssim = point.get("val_psnr"), point.get("val_ssim")
            rows.append(f"| {label} | {gop['gop']} | {point['iteration']} | {point['seconds'] / 60:.1f} "
                        f"| {point['loss']:.4f} | {_num(psnr, '.2f')} | {_num(ssim, '.4f')} |")
    return rows


def gop_rows(label: str, report: dict) -> list[str]:
    return [f"| {label} | {gop['gop']} | {gop['iterations']} | {gop['seconds'] / 60:.1f} | {gop['train_psnr']:.2f} "
            f"| {_num(gop.get('val_psnr'), '.2f')} | {_num(gop.get('val_ssim'), '.4f')} | {gop['relocated']} "
            f"| {gop['pruned']} |" for gop in report["gops"]]


def eval_rows(label: str, evaluation: dict) -> list[str]:
    rows = []
    for stream, result in evaluation["streams"].items():
        for gop in result["gops"]:
            regions = f"{_num(gop.get('psnr_foreground'), '.2f')} / {_num(gop.get('psnr_background'), '.2f')}"
            rows.append(f"| {label} | {stream} | {gop['gop']} | {gop['psnr']:.2f} | {gop['ssim']:.4f} "
                        f"| {_num(gop.get('lpips'), '.4f')} | {regions} | {len(gop['frames'])} |")
    return rows


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def plot(runs: list[tuple[str, dict]], path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for label, report in runs:
        for gop in report["gops"]:
            points = [p for p in gop["curve"] if p.get("val_psnr") is not None]
            minutes = [p["seconds"] / 60 for p in points]
            name = f"{label}, GOP {gop['gop']}" if len(report["gops"]) > 1 else label
            axes[0].plot(minutes, [p["val_psnr"] for p in points], "o-", label=name)
            axes[1].plot(minutes, [p.get("val_ssim") for p in points], "o-", label=name)
    for ax, metric in zip(axes, ("PSNR (dB)", "SSIM"), strict=True):
        ax.set_xlabel("training time (min, this machine)")
        ax.set_ylabel(f"held-out {metric}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("stgs train: held-out quality vs training time")
    fig.tight_layout()
    save_figure(fig, path)


def main(model_dirs: list[Path], plot_path: Path) -> int:
    runs = []
    for model_dir in model_dirs:
        report_path = model_dir / TRAIN_REPORT
        if not report_path.is_file():
            raise StgsError(f"{model_dir}: no train_report.json (not a finished stgs train run)")
        runs.append((model_dir, run_label(model_dir), _read_json(report_path)))
    labels = distinct_labels([d for d, _, _ in runs], [label for _, label, _ in runs])
    runs = [(d, label, report) for (d, _, report), label in zip(runs, labels, strict=True)]
    print("| run | GOP | iteration | training min | loss | held-out PSNR (dB) | held-out SSIM |")
    print("|---|---|---|---|---|---|---|")
    for _, label, report in runs:
        print("\n".join(curve_rows(label, report)))
    print()
    print("| run | GOP | iterations | training min | train PSNR (dB) | held-out PSNR (dB) | held-out SSIM "
          "| relocated | pruned |")
    print("|---|---|---|---|---|---|---|---|---|")
    for _, label, report in runs:
        print("\n".join(gop_rows(label, report)))
    evaluated = [(label, _read_json(d / "eval.json")) for d, label, _ in runs if (d / "eval.json").is_file()]
    if evaluated:
        print()
        print("| run | stream | GOP | PSNR (dB) | SSIM | LPIPS | foreground / background PSNR (dB) "
              "| frames x cameras |")
        print("|---|---|---|---|---|---|---|---|")
        for label, evaluation in evaluated:
            print("\n".join(eval_rows(label, evaluation)))
    plot([(label, report) for _, label, report in runs], plot_path)
    print(f"\n<!-- plot: {plot_path} -->")
    return 0
