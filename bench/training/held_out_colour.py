"""How much of a trained scene's held-out error is the held-out camera's own colour response
(`python -m bench.training.held_out_colour --models DIR,... --dataset D`, prints Markdown rows for docs/BENCHMARKS.md).

A real rig's cameras differ in gain and white balance. Training learns each training camera's response
(stgs.train.camera_colour) and the scene keeps the average camera's colour, which is what a camera the model was
never shown is drawn in; its own response no model can know. This measures that share of the error: per held-out
camera, one gain and offset per channel are fitted by least squares (render -> image) over half of its views (every
other sampled view, `stgs eval`'s views at `--stride`) and the other half is scored as drawn and through that
response (not clamped), over the whole frame and outside the dataset's foreground masks. An oracle on the held-out
images, so a diagnostic only: `stgs eval` never applies it.

The fit also takes up whatever part of the model's own error is linear in the drawn value. `--cameras` names
training cameras instead, whose responses training learnt (train_report.json's `camera_colour`, printed beside the
fit): how far the fit lands from the learnt response there is what it takes up from the model.
"""

from __future__ import annotations

import argparse
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from stgs.data import Dataset

IDENTITY = (torch.ones(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))


@dataclass
class ColourSums:
    """Per-channel sums over the pixels of some views: x (drawn), y (recorded), xx, xy, yy and the pixel count."""

    sums: torch.Tensor = field(default_factory=lambda: torch.zeros(6, 3, dtype=torch.float64))

    @classmethod
    def of(cls, image: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor | None = None) -> ColourSums:
        """The sums of (H, W, 3) `image` against `truth`, over the pixels of an (H, W) bool `mask` when given."""
        x, y = image.double().reshape(-1, 3), truth.double().reshape(-1, 3)
        if mask is not None:
            x, y = x[mask.reshape(-1)], y[mask.reshape(-1)]
        n = torch.full((3,), float(x.shape[0]), dtype=torch.float64)
        return cls(torch.stack([x.sum(0), y.sum(0), (x * x).sum(0), (x * y).sum(0), (y * y).sum(0), n]))

    def __add__(self, other: ColourSums) -> ColourSums:
        return ColourSums(self.sums + other.sums)

    def fit(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-channel (gain, offset) minimising the squared error of gain · x + offset against y; where the drawn
        values do not vary, gain 1 and the mean difference."""
        sx, sy, sxx, sxy, _, n = self.sums
        n = n.clamp(min=1)
        var = sxx - sx * sx / n
        flat = var <= 1e-12 * n
        gain = torch.where(flat, torch.ones_like(var), (sxy - sx * sy / n) / torch.where(flat, 1, var))
        return gain, (sy - gain * sx) / n

    def mse(self, gain: torch.Tensor, offset: torch.Tensor) -> float:
        """Mean over pixels and channels of (gain · x + offset − y)²; nan over no pixels."""
        sx, sy, sxx, sxy, syy, n = self.sums
        if float(n[0]) == 0:
            return math.nan
        err = gain * gain * sxx + offset * offset * n + syy + 2 * gain * offset * sx - 2 * gain * sxy - 2 * offset * sy
        return float(err.clamp(min=0).sum() / n.sum())


def psnr_of(mse: float) -> float:
    """PSNR in dB (peak 1) of a mean squared error: inf for 0, nan for nan."""
    if math.isnan(mse):
        return math.nan
    return math.inf if mse == 0 else -10 * math.log10(mse)


@dataclass
class CameraViews:
    """One camera's views: the sums its response is fitted on, and the scored views' sums."""

    fit_on: ColourSums = field(default_factory=ColourSums)
    scored: list[tuple[ColourSums, ColourSums | None]] = field(default_factory=list)
    """Per scored view: (whole frame, outside the foreground mask or None without masks)."""

    def scores(self) -> dict[str, float | list[float]]:
        """The fitted gain and offset; per region (whole, background) the scored views' mean PSNR drawn and
        through that response, and the share of their squared error it removes."""
        gain, offset = self.fit_on.fit()
        out: dict[str, float | list[float]] = {"gain": gain.tolist(), "offset": offset.tolist()}
        for key, index in (("whole", 0), ("background", 1)):
            views = [v[index] for v in self.scored if v[index] is not None]
            for label, response in (("drawn", IDENTITY), ("fitted", (gain, offset))):
                values = [psnr_of(v.mse(*response)) for v in views]
                out[f"{key}_{label}"] = sum(values) / len(values) if values else math.nan
            drawn = sum(v.mse(*IDENTITY) for v in views)
            out[f"{key}_share"] = 1 - sum(v.mse(gain, offset) for v in views) / drawn if drawn else math.nan
        return out


def check_cameras(ds: Dataset, names: list[str]) -> None:
    """Exits with one line naming the cameras of `names` that dataset `ds` lacks."""
    unknown = sorted(set(names) - set(ds.camera_names))
    if unknown:
        raise SystemExit(f"{ds.name}: no camera(s) {unknown}")


def held_out_views(model_dir: Path, dataset: Path, stride: int,
                   names: list[str] | None = None) -> dict[str, CameraViews]:
    """Per camera of `names` (default: the held-out cameras of `model_dir`): its views' sums, every `stride`-th
    frame of every GOP."""
    from stgs.data import open_dataset
    from stgs.evaluate import scaled_view
    from stgs.model.renderer import FrameRenderer
    from stgs.model.store import load_gop, load_static, read_meta

    meta = read_meta(model_dir)
    extra = meta.extra or {}
    ds = open_dataset(dataset)
    names = names or extra.get("validation_cameras") or list(ds.default_holdout)
    check_cameras(ds, names)
    start = int(extra.get("start_frame", 0))
    scale = float((extra.get("config") or {}).get("scale", 1.0))
    static = load_static(model_dir, meta)
    cameras = {name: CameraViews() for name in names}
    sampled = 0
    for k in range(meta.num_gops):
        renderer = FrameRenderer(load_gop(model_dir, meta, k), static=static)
        for i in range(0, meta.shape.gop_size, stride):
            f = start + k * meta.shape.gop_size + i
            by_name = {c.name: c for c in ds.cameras(f)}
            for name in names:
                cam, truth = scaled_view(ds, by_name[name], f, scale)
                image = renderer.render(i, cam).clamp(0, 1)
                whole = ColourSums.of(image, truth)
                if sampled % 2 == 0:  # alternate frames: fit on one half, score the other
                    cameras[name].fit_on += whole
                else:
                    mask = ds.mask(f, name)
                    cameras[name].scored.append((whole, None if mask is None else ColourSums.of(image, truth, ~mask)))
            sampled += 1
    return cameras


def learnt_responses(model_dir: Path) -> dict[str, list[float]]:
    """Training camera -> its learnt (3 gains, 3 offsets) from the scene's train_report.json ({} without one)."""
    import json

    from stgs.tree import TRAIN_REPORT

    report = model_dir / TRAIN_REPORT
    if not report.is_file():
        return {}
    return json.loads(report.read_text()).get("camera_colour") or {}


def response(values: list[float]) -> str:
    """'gains / offsets' of three gains then three offsets."""
    return "/".join(f"{g:.3f}" for g in values[:3]) + " | " + "/".join(f"{o:+.3f}" for o in values[3:])


def rows(model_dir: Path, dataset: Path, stride: int, names: list[str] | None = None) -> list[str]:
    cameras = held_out_views(model_dir, dataset, stride, names)
    learnt = learnt_responses(model_dir)
    scores = {name: views.scores() for name, views in cameras.items()}
    out = []
    for name, s in scores.items():
        known = response(learnt[name]) if name in learnt else "- | -"
        out.append(f"| {model_dir.name} | {name} | {known} | {response([*s['gain'], *s['offset']])} | "
                   f"{s['whole_drawn']:.2f} | "
                   f"{s['whole_fitted']:.2f} | {s['background_drawn']:.2f} | {s['background_fitted']:.2f} | "
                   f"{100 * s['whole_share']:.0f} % |")
    mean = {key: sum(s[key] for s in scores.values()) / len(scores)
            for key in ("whole_drawn", "whole_fitted", "background_drawn", "background_fitted")}
    out.append(f"| {model_dir.name} | all | | | | | {mean['whole_drawn']:.2f} | {mean['whole_fitted']:.2f} | "
               f"{mean['background_drawn']:.2f} | {mean['background_fitted']:.2f} | |")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", required=True, help="comma-separated trained scenes")
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--stride", type=int, default=3, help="every n-th frame of each GOP, as `stgs eval --stride`")
    parser.add_argument("--cameras", help="comma-separated cameras to fit (default: each scene's held-out ones)")
    args = parser.parse_args()
    names = args.cameras.split(",") if args.cameras else None
    if names:  # before the table's header, so that a wrong name prints nothing else
        from stgs.data import open_dataset

        check_cameras(open_dataset(args.dataset), names)
    print(f"machine: {platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}")
    print("| scene | camera | learnt gain R/G/B | learnt offset R/G/B | fitted gain R/G/B | fitted offset R/G/B | "
          "PSNR drawn | PSNR through the fitted response | background drawn | background fitted | share of the MSE |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for model in args.models.split(","):
        print("\n".join(rows(Path(model), args.dataset, args.stride, names)), flush=True)


if __name__ == "__main__":
    main()
