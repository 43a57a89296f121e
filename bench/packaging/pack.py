"""Packager benchmark: rate, distortion and codec time per QP and x265 preset,
PLAS vs no sort, and the PLAS sort itself (`stgs bench pack`).

Prints Markdown tables for docs/BENCHMARKS.md and writes rate-distortion
plots (matplotlib PNG).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from stgs.codec.mp4 import split_fragmented
from stgs.codec.plas import neighbour_distance, plas_order
from stgs.codec.plas_config import PLASConfig
from stgs.codec.video import HEVC, decode_segment, encode_gop
from stgs.fsio import save_figure
from stgs.metrics import psnr
from stgs.packager.packer import PackConfig, Packer
from stgs.packager.segments import measure
from stgs.synth import PRESETS, SynthConfig, synthesize
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.synth.scene import ProceduralScene


def codec_rows(model_dir: Path, out: Path, qps: list[int], presets: list[str], sort: bool) -> list[dict]:
    """One row per (preset, QP): sizes, PSNRs and codec times, averaged over GOPs."""
    rows = []
    for preset in presets:
        cfg = PackConfig(ladder="fixed", qps=tuple(qps), preset=preset, sort=sort, codecs=("hevc",), jobs=1)
        packer = Packer(model_dir, out / f"{preset}-{sort}", cfg, progress=False)
        shape = packer.meta.shape
        per_qp: dict[int, list[dict]] = {qp: [] for qp in qps}
        for k in range(packer.meta.num_gops):
            gop = packer.prepare_gop(k)
            for qp in qps:
                start = time.perf_counter()
                init, media = packer.encoder.encode(k, HEVC, qp, gop.frames[HEVC.bits])
                encode_s = time.perf_counter() - start
                start = time.perf_counter()
                decode_segment(init, media, shape.num_features, 4 * packer.side, 4 * packer.side)
                decode_s = time.perf_counter() - start
                m = measure(gop, HEVC, init, media, packer.meta)
                per_qp[qp].append({**m, "keyframe_bytes": len(gop.keyframe), "encode_s": encode_s,
                                   "decode_s": decode_s})
            packer.encoder.init_segments.clear()
        for qp in qps:
            runs = per_qp[qp]
            g = shape.gop_size
            rows.append({
                "preset": preset, "qp": qp, "sort": sort,
                "feature_kb_per_frame": statistics.mean(r["bytes"] for r in runs) / g / 1024,
                "total_kb_per_frame": statistics.mean(r["bytes"] + r["keyframe_bytes"] for r in runs) / g / 1024,
                "feature_psnr": statistics.mean(r["feature_psnr"] for r in runs),
                "render_psnr": statistics.mean(r["render_psnr"] for r in runs),
                "encode_ms_per_frame": statistics.mean(r["encode_s"] for r in runs) / shape.num_features * 1e3,
                "decode_ms_per_frame": statistics.mean(r["decode_s"] for r in runs) / shape.num_features * 1e3,
            })
    return rows


def qp_vs_crf_rows(model_dir: Path, out: Path, values: list[int]) -> list[dict]:
    """GOP 0 at preset medium: constant QP vs CRF of the same value, sizes and feature PSNR."""
    packer = Packer(model_dir, out / "crf", PackConfig(ladder="fixed",
                                                       qps=tuple(values), codecs=("hevc",), jobs=1), progress=False)
    frames = packer.prepare_gop(0).frames[HEVC.bits]
    shape = packer.meta.shape
    rows = []
    for value in values:
        row = {"value": value}
        for mode in ("qp", "crf"):
            init, media = split_fragmented(encode_gop(frames, value, packer.timing, "medium", crf=mode == "crf"))
            decoded = decode_segment(init, media, shape.num_features, 4 * packer.side, 4 * packer.side)
            row[f"{mode}_kb"] = len(media) / 1024
            row[f"{mode}_psnr"] = psnr(torch.from_numpy(decoded.astype("float32")) / 4095,
                                       torch.from_numpy(frames.astype("float32")) / 4095)
        rows.append(row)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for preset, sort in dict.fromkeys((r["preset"], r["sort"]) for r in rows):
        sel = [r for r in rows if r["preset"] == preset and r["sort"] == sort]
        label = f"{preset}{'' if sort else ', no PLAS'}"
        ls = "-" if sort else "--"
        axes[0].plot([r["feature_kb_per_frame"] for r in sel], [r["feature_psnr"] for r in sel], ls,
                     marker="o", label=label)
        axes[1].plot([r["total_kb_per_frame"] for r in sel], [r["render_psnr"] for r in sel], ls,
                     marker="o", label=label)
    axes[0].set(xlabel="feature video KB / frame", ylabel="decoded features PSNR (dB)",
                title="Feature video rate-distortion")
    axes[1].set(xlabel="total KB / frame (keyframe + features)", ylabel="rendered views PSNR (dB)",
                title="Rendered views vs uncompressed model")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def plas_rows(sides: list[int]) -> list[dict]:
    """Smoothness and time of PLAS on the synthetic scene's attributes at S x S."""
    rows = []
    for side in sides:
        n = side * side
        truth = ProceduralScene(n, DEFAULT_EFFECTS, seed=0).at(0.0)
        key = torch.cat([truth.means, truth.base_colors, truth.log_scales, truth.quats,
                         truth.opacities[:, None]], 1)
        key = (key - key.mean(0)) / key.std(0).clamp_min(1e-6)
        start = time.perf_counter()
        order = plas_order(key, side, PLASConfig())
        seconds = time.perf_counter() - start
        rand = neighbour_distance(key[torch.randperm(n, generator=torch.Generator().manual_seed(0))], side)
        rows.append({"side": side, "n": n, "seconds": seconds, "random": rand,
                     "plas": neighbour_distance(key[order], side)})
    return rows


def main(qps: list[int], presets: list[str], sides: list[int], plot_path: Path,
         scene: SynthConfig | None = None) -> int:
    scene = scene or PRESETS["demo"]
    with tempfile.TemporaryDirectory() as tmp:
        model_dir = Path(tmp) / "scene"
        synthesize(scene, model_dir, progress=False)
        rows = codec_rows(model_dir, Path(tmp), qps, presets, sort=True)
        rows += codec_rows(model_dir, Path(tmp), qps, ["medium"], sort=False)
        crf_rows = qp_vs_crf_rows(model_dir, Path(tmp), qps)
    print(f"<!-- stgs bench pack: synthetic scene, {scene.grid_side ** 2} Gaussians, {scene.num_gops} GOPs x "
          f"{scene.gop_size} frames, views {scene.width}x{scene.height}, {torch.get_num_threads()} threads -->")
    print("| preset | PLAS | QP | features KB/frame | total KB/frame | features PSNR dB | rendered PSNR dB "
          "| encode ms/frame | decode ms/frame |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['preset']} | {'yes' if r['sort'] else 'no'} | {r['qp']} | {r['feature_kb_per_frame']:.2f} "
              f"| {r['total_kb_per_frame']:.2f} | {r['feature_psnr']:.2f} | {r['render_psnr']:.2f} "
              f"| {r['encode_ms_per_frame']:.1f} | {r['decode_ms_per_frame']:.2f} |")
    plot(rows, plot_path)
    print(f"\nplot: {plot_path}\n")
    print("| value | constant QP: KB (GOP 0) | QP: features PSNR dB | CRF: KB | CRF: features PSNR dB |")
    print("|---|---|---|---|---|")
    for r in crf_rows:
        print(f"| {r['value']} | {r['qp_kb']:.1f} | {r['qp_psnr']:.2f} | {r['crf_kb']:.1f} | {r['crf_psnr']:.2f} |")
    print()
    print("| S | N | PLAS seconds | mean neighbour distance, random order | after PLAS | ratio |")
    print("|---|---|---|---|---|---|")
    for r in plas_rows(sides):
        print(f"| {r['side']} | {r['n']} | {r['seconds']:.1f} | {r['random']:.3f} | {r['plas']:.3f} "
              f"| {r['plas'] / r['random']:.2f} |", flush=True)
    return 0
