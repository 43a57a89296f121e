"""Feature codecs at equal bytes: 12-bit HEVC (the reference ladder) against 10-bit AV1 (what browsers decode)
and, as the candidate the choice was made against, VP9 profile 2 at 12 bits (Debian's ffmpeg with libvpx; not in
PyAV's wheel, so not a packager codec).

    python -m bench.packaging.codecs MODEL_DIR [MODEL_DIR ...] [--gops 1]

Per model dir and GOP (PLAS-sorted as the packager sorts it): the 12 -> 10-bit step alone (no video codec),
then per ladder point of each codec the feature KB/frame, the rendered PSNR against the uncompressed model (the
packager's stats views), encode seconds per GOP (one thread, as the packager runs each encode) and decode ms per
frame in the Python player's path (PyAV decode + dequantise, one thread); then each HEVC rung against the other
codecs' PSNR interpolated at its bytes (linear in log bytes), and `stgs pack` with both sets against HEVC alone.
Prints Markdown for docs/BENCHMARKS.md ("Feature codecs").
"""

from __future__ import annotations

import argparse
import itertools
import math
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from stgs.codec.features import dequantize_frame
from stgs.codec.mp4 import split_fragmented
from stgs.codec.video import AV1, HEVC, FeatureCodec, encode_gop, iter_frames
from stgs.packager import PackConfig, pack
from stgs.packager.packer import Packer
from stgs.packager.segments import PreparedGOP, quality

AV1_SWEEP = (8, 12, 16, 19, 23, 27, 31, 35, 39, 43, 48)
VP9_SWEEP = (8, 16, 24, 32, 40, 48, 56)


def encode_decode(gop: PreparedGOP, packer: Packer, codec: FeatureCodec, q: int) -> dict:
    frames = gop.frames[codec.bits]
    e, size, side = frames.shape[0], frames.shape[1], frames.shape[1] // 4
    start = time.perf_counter()
    init, media = split_fragmented(encode_gop(frames, q, packer.timing, codec=codec))
    encode_s = time.perf_counter() - start
    decoded, spent = np.empty_like(frames), 0.0
    start = time.perf_counter()
    for i, frame in enumerate(iter_frames(init + media, e, size, size, threads=1, codec=codec)):
        decoded[i] = frame
        dequantize_frame(frame, side, gop.ranges, bits=codec.bits)
    spent = time.perf_counter() - start
    return {"codec": codec.name, "q": q, "bytes": len(media), "encode_s": encode_s, "decode_ms": spent / e * 1e3,
            **quality(gop, decoded, codec.bits, packer.static)}


def vp9_12bit(gop: PreparedGOP, packer: Packer, crf: int, tmp: Path) -> dict:
    """VP9 profile 2, 4:2:0 12-bit, the features in luma (Debian's ffmpeg binary; one thread, closed GOP)."""
    frames = gop.frames[12]
    e, size = frames.shape[0], frames.shape[1]
    chroma = np.full((e, size // 2, size), 2048, np.uint16)  # both quarter planes, neutral
    raw = np.concatenate([frames, chroma], axis=1).tobytes()
    ivf = tmp / "vp9.ivf"
    rate = f"{packer.timing.rate.numerator}/{packer.timing.rate.denominator}"
    start = time.perf_counter()
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "yuv420p12le", "-s", f"{size}x{size}",
                    "-framerate", rate, "-i", "pipe:", "-c:v", "libvpx-vp9", "-pix_fmt", "yuv420p12le",
                    "-crf", str(crf), "-b:v", "0", "-g", str(e), "-keyint_min", str(e), "-threads", "1",
                    "-row-mt", "0", "-deadline", "good", "-cpu-used", "2", str(ivf)], input=raw, check=True)
    encode_s = time.perf_counter() - start
    out = subprocess.run(["ffmpeg", "-v", "error", "-i", str(ivf), "-f", "rawvideo", "-pix_fmt", "yuv420p12le",
                          "-fps_mode", "passthrough", "-"], capture_output=True, check=True).stdout
    decoded = np.frombuffer(out, np.uint16).reshape(e, -1)[:, :size * size].reshape(e, size, size)
    stream_bytes = ivf.stat().st_size - 32 - 12 * e  # less the IVF file and frame headers
    return {"codec": "vp9", "q": crf, "bytes": stream_bytes, "encode_s": encode_s, "decode_ms": math.nan,
            **quality(gop, decoded.copy(), 12, packer.static)}


def at_bytes(rows: list[dict], target: float) -> float | None:
    """A codec's rendered PSNR at `target` bytes, linear in log bytes between its two nearest points."""
    pts = sorted((math.log(r["bytes"]), r["render_psnr"]) for r in rows)
    x = math.log(target)
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        if x0 <= x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return None


def pack_times(model: Path, tmp: Path) -> tuple[float, float]:
    times = []
    for codecs in (("hevc",), ("hevc", "av1")):
        start = time.perf_counter()
        pack(model, tmp / "-".join(codecs), PackConfig(ladder="fixed", codecs=codecs, jobs=2), progress=False)
        times.append(time.perf_counter() - start)
    return times[0], times[1]


def report(model: Path, gops: int, vp9: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        packer = Packer(model, tmp / "work", PackConfig(ladder="fixed", codecs=("hevc", "av1"), jobs=1), progress=False)
        g, side = packer.meta.shape.gop_size, packer.side
        rows: list[dict] = []
        steps = []
        for k in range(min(gops, packer.meta.num_gops)):
            gop = packer.prepare_gop(k)
            twelve, ten = quality(gop, gop.frames[12], 12, packer.static), quality(gop, gop.frames[10], 10,
                                                                                    packer.static)
            steps.append((twelve, ten))
            rows += [{**encode_decode(gop, packer, HEVC, q), "gop": k} for q in HEVC.ladder]
            rows += [{**encode_decode(gop, packer, AV1, q), "gop": k} for q in AV1_SWEEP]
            if vp9:
                rows += [{**vp9_12bit(gop, packer, crf, tmp), "gop": k} for crf in VP9_SWEEP]
        hevc_alone, both = pack_times(model, tmp)
    print(f"\n### {model.name}: {packer.meta.shape.capacity} Gaussians (4S = {4 * side}), "
          f"{min(gops, packer.meta.num_gops)} GOP(s) of {g} frames\n")
    print("The 12 -> 10-bit step alone (uncompressed codes, per-channel ranges, no dither):\n")
    print("| codes | feature PSNR dB | rendered PSNR dB |\n|---|---|---|")
    for name, i in (("12-bit", 0), ("10-bit", 1)):
        print(f"| {name} | {np.mean([s[i]['feature_psnr'] for s in steps]):.2f} | "
              f"{np.mean([s[i]['render_psnr'] for s in steps]):.2f} |")
    print("\n| codec | ladder point | feature KB/frame | rendered PSNR dB | encode s/GOP | decode ms/frame |")
    print("|---|---|---|---|---|---|")
    by = {}
    for r in rows:
        by.setdefault((r["codec"], r["q"]), []).append(r)
    for (codec, q), rs in by.items():
        decode = np.mean([r["decode_ms"] for r in rs])
        print(f"| {codec} | {q} | {np.mean([r['bytes'] for r in rs]) / g / 1024:.2f} | "
              f"{np.mean([r['render_psnr'] for r in rs]):.2f} | {np.mean([r['encode_s'] for r in rs]):.2f} | "
              f"{'n/a' if math.isnan(decode) else f'{decode:.2f}'} |")
    print("\nAt each HEVC rung's bytes (per GOP, then the mean):\n")
    others = ["av1", "vp9"] if vp9 else ["av1"]
    print("| HEVC QP | KB/frame | HEVC dB | " + " | ".join(f"{o} dB (delta)" for o in others) + " |")
    print("|---|---|---|" + "---|" * len(others))
    for q in HEVC.ladder:
        cells, kb, ref = {o: [] for o in others}, [], []
        for r in by[("hevc", q)]:
            kb.append(r["bytes"] / g / 1024)
            ref.append(r["render_psnr"])
            for o in others:
                cells[o].append(at_bytes([x for x in rows if x["codec"] == o and x["gop"] == r["gop"]], r["bytes"]))
        line = f"| {q} | {np.mean(kb):.2f} | {np.mean(ref):.2f} |"
        for o in others:
            if None in cells[o]:
                line += " out of its sweep |"
            else:
                line += f" {np.mean(cells[o]):.2f} ({np.mean(cells[o]) - np.mean(ref):+.2f}) |"
        print(line)
    print(f"\n`stgs pack` (--jobs 2, every GOP): HEVC alone {hevc_alone:.1f} s, HEVC + AV1 {both:.1f} s "
          f"({both / hevc_alone:.2f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, help="model dirs")
    parser.add_argument("--gops", type=int, default=1, help="GOPs per model (default: 1)")
    parser.add_argument("--no-vp9", action="store_true", help="skip VP9 (needs Debian's ffmpeg with libvpx)")
    args = parser.parse_args()
    for model in args.models:
        report(model, args.gops, not args.no_vp9)


if __name__ == "__main__":
    main()
