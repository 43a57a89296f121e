"""Synthetic-scene fit: fidelity vs fit iterations (`stgs bench synth`).

Each row synthesises the same scene with a different number of Adam steps per
GOP and reports the parameter errors of the fit, the rendered fidelity
against the ground truth, and the fit time.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

from stgs.synth import PRESETS, synthesize


def main(steps: list[int], preset: str = "small") -> int:
    base = PRESETS[preset]
    print(f"<!-- stgs bench synth: preset {preset}: {base.grid_side ** 2} Gaussians, {base.num_gops} GOPs x "
          f"{base.gop_size} frames, {base.width}x{base.height}, {base.num_cameras} cameras -->")
    print("| fit steps per GOP | fit seconds per GOP | position RMSE | colour RMSE | opacity RMSE "
          "| fidelity PSNR dB |")
    print("|---|---|---|---|---|---|")
    for n in steps:
        cfg = dataclasses.replace(base, fit_steps=n)
        with tempfile.TemporaryDirectory() as tmp:
            report = synthesize(cfg, Path(tmp) / "scene", progress=False)
        fits = report.fit
        mean = {k: sum(f[k] for f in fits) / len(fits)
                for k in ("seconds", "position_rmse", "color_rmse", "opacity_rmse")}
        print(f"| {n} | {mean['seconds']:.1f} | {mean['position_rmse']:.2e} | {mean['color_rmse']:.2e} "
              f"| {mean['opacity_rmse']:.2e} | {report.fidelity_psnr:.2f} |", flush=True)
    return 0
