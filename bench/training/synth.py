"""Synthetic-scene fit: fidelity vs fit iterations, and what the fit's feature smoothness buys in feature bits
and decode time (`stgs bench synth`).

The first table synthesises the same scene with a different number of Adam steps per GOP and reports the
parameter errors of the fit, the rendered fidelity against the ground truth, and the fit time. The second
(`--smoothness`) synthesises it with each weight of the fit's feature roughness term, packs it at the QPs
and reports per QP the feature bitrate, the rendered PSNR against the uncompressed model (stats.json) and the
feature decode time per frame (one libavcodec thread, best of three passes over the first GOP's segment).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

from stgs.codec.video import iter_frames
from stgs.model.store import read_meta
from stgs.packager import PackConfig, pack
from stgs.synth import PRESETS, SynthConfig, synthesize
from stgs.tree import feature_path, rep_id, version_dir


def main(steps: list[int], preset: str = "small", smoothness: list[float] | None = None,
         qps: list[int] | None = None) -> int:
    base = PRESETS[preset]
    print(f"<!-- stgs bench synth: preset {preset}: {base.grid_side ** 2} Gaussians, {base.num_gops} GOPs x "
          f"{base.gop_size} frames, {base.width}x{base.height}, {base.num_cameras} cameras -->")
    if smoothness:
        return smoothness_table(base, smoothness, qps or [16, 24, 32])
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


def decode_ms(tree: Path, pack_id: str, qp: int, side: int, frames: int) -> float:
    """Milliseconds per feature frame of GOP 0's segment at `qp`, one decoder thread, best of three passes."""
    version = version_dir(pack_id)
    data = (tree / feature_path(version, rep_id(qp), None)).read_bytes()
    data += (tree / feature_path(version, rep_id(qp), 0)).read_bytes()
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for _frame in iter_frames(data, frames, 4 * side, 4 * side, threads=1):
            pass
        best = min(best, (time.perf_counter() - start) / frames)
    return best * 1e3


def smoothness_table(base: SynthConfig, weights: list[float], qps: list[int]) -> int:
    head = " | ".join(f"QP {q}: Mbit/s, rendered dB, decode ms" for q in qps)
    print(f"| feature smoothness | fit seconds per GOP | fidelity PSNR dB | {head} |")
    print("|---|---|---|" + "---|" * len(qps))
    for weight in weights:
        cfg = dataclasses.replace(base, feature_smoothness=weight)
        with tempfile.TemporaryDirectory() as tmp:
            scene, tree = Path(tmp) / "scene", Path(tmp) / "dash"
            report = synthesize(cfg, scene, progress=False)
            stats = pack(scene, tree, PackConfig(ladder="fixed", qps=tuple(qps)), progress=False)
            shape = read_meta(scene).shape
            cells = []
            for q in qps:
                rep = stats["representations"][rep_id(q)]
                ms = decode_ms(tree, stats["pack_id"], q, shape.grid_side, shape.num_features)
                cells.append(f"{rep['bandwidth'] / 1e6:.2f}, {rep['mean_render_psnr']:.2f}, {ms:.1f}")
        seconds = sum(f["seconds"] for f in report.fit) / len(report.fit)
        print(f"| {weight:g} | {seconds:.1f} | {report.fidelity_psnr:.2f} | {' | '.join(cells)} |", flush=True)
    return 0
