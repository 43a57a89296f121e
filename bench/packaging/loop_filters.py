"""HEVC's in-loop filters on the feature video: bytes, fidelity and decode time with deblocking + SAO and without
(`python -m bench.packaging.loop_filters --model DIR [--model DIR ...]`, prints Markdown rows for docs/BENCHMARKS.md).

The deblocking filter and SAO are tuned for what people see in pictures; a feature frame is data. Per model,
per GOP (the first `--gops`) and per QP, the GOP's sorted feature frames are encoded at the packager's preset
with the filters (the default) and without (`stgs pack --no-loop-filters`). Per setting: the media segment's
KB per played frame, the decoded features' PSNR and the rendered views' PSNR against the uncompressed model
(the packager's own `measure`), and the single-threaded decode time per feature frame (the player's decoder
thread), the two settings decoded alternately `--repeats` times, medians.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from stgs.codec.video import HEVC, decode_segment
from stgs.packager.packer import PackConfig, Packer
from stgs.packager.segments import FeatureEncoder, measure

SETTINGS = (True, False)
"""Loop filters on (the packager's default), then off."""


def rows_for(model_dir: Path, qps: list[int], gops: int, repeats: int) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        packer = Packer(model_dir, Path(tmp) / "dash", PackConfig(ladder="fixed",
                                                                  qps=tuple(qps), codecs=("hevc",), jobs=1),
                        progress=False)
        shape, side = packer.meta.shape, packer.side
        encoders = {on: FeatureEncoder(packer.timing, shape.num_features, packer.cfg.preset_of, on) for on in SETTINGS}
        static = packer.static  # the uncompressed static layer: only the features differ between settings
        acc: dict[tuple[int, bool], list[dict]] = {}
        for k in range(min(gops, packer.meta.num_gops)):
            gop = packer.prepare_gop(k)
            for qp in qps:
                segments = {on: encoders[on].encode(k, HEVC, qp, gop.frames[HEVC.bits]) for on in SETTINGS}
                times: dict[bool, list[float]] = {on: [] for on in SETTINGS}
                for _ in range(repeats):
                    for on in SETTINGS:
                        start = time.perf_counter()
                        decode_segment(*segments[on], shape.num_features, 4 * side, 4 * side, threads=1)
                        times[on].append(time.perf_counter() - start)
                for on in SETTINGS:
                    m = measure(gop, HEVC, *segments[on], packer.meta, static)
                    acc.setdefault((qp, on), []).append(
                        {**m, "decode_s": statistics.median(times[on])})
            for enc in encoders.values():
                enc.init_segments.clear()
    g, e = shape.gop_size, shape.num_features
    return [{"model": model_dir.name, "gaussians": shape.capacity, "frame_side": 4 * side, "qp": qp,
             "filters": on, "gops": len(runs),
             "kb_per_frame": statistics.mean(r["bytes"] for r in runs) / g / 1024,
             "feature_psnr": statistics.mean(r["feature_psnr"] for r in runs),
             "render_psnr": statistics.mean(r["render_psnr"] for r in runs),
             "decode_ms": statistics.mean(r["decode_s"] for r in runs) / e * 1e3}
            for (qp, on), runs in sorted(acc.items(), key=lambda item: (item[0][0], not item[0][1]))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="model dir (repeatable)")
    parser.add_argument("--qps", default="16,24,32", help="comma-separated QPs (default: 16,24,32)")
    parser.add_argument("--gops", type=int, default=2, help="GOPs per model, from the first (default: 2)")
    parser.add_argument("--repeats", type=int, default=5, help="decodes per setting, alternating (default: 5)")
    args = parser.parse_args(argv)
    qps = [int(q) for q in args.qps.split(",")]
    print(f"<!-- python -m bench.packaging.loop_filters ({platform.processor() or platform.machine()}), "
          f"{torch.get_num_threads()} threads -->")
    print("| scene | Gaussians | frame | QP | deblock + SAO | GOPs | features KB/frame | features PSNR dB "
          "| rendered PSNR dB | decode ms/frame (1 thread) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for model_dir in args.model:
        for r in rows_for(model_dir, qps, args.gops, args.repeats):
            print(f"| {r['model']} | {r['gaussians']:,} | {r['frame_side']}² | {r['qp']} "
                  f"| {'on' if r['filters'] else 'off'} | {r['gops']} | {r['kb_per_frame']:.2f} "
                  f"| {r['feature_psnr']:.2f} | {r['render_psnr']:.2f} | {r['decode_ms']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
