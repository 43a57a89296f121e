#!/usr/bin/env python3
"""Feature-video encode and decode: the project's route (PyAV in-process, stgs.codec.video) against the ffmpeg
binary through a pipe (Debian's ffmpeg, the route the project used before): the measurement behind the choice.

Per grid side, one GOP of E = 62 smooth 12-bit gray frames (the shape a PLAS-sorted feature video has):
- encode: the packager's settings (constant QP, closed GOP, one x265 thread) by each route, `--rounds` times,
  order alternating; segment size and PSNR of the decoded frames against the input (the two routes link
  different libx265 builds);
- decode: the project's encode decoded by each route, `--rounds` times, order alternating: time to the first
  frame (what a frame-by-frame player waits for at a GOP boundary) and to the last; both give the same uint16
  frames (checked). Decoders run with their default threading.

Needs Debian's ffmpeg binary on PATH (bin/test installs it).

Usage: .venv/bin/python -m bench.packaging.video_io [--sides 256 512 1024] [--rounds 3] [--qp 20] [--preset medium]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from stgs.codec.video import PIXEL_FORMAT, VideoTiming, encode_gop, iter_frames, x265_params

FRAMES = 62
TIMING = VideoTiming.for_gop(FRAMES, 60, 30.0)


def smooth_frames(side: int, seed: int = 0) -> np.ndarray:
    """(FRAMES, side, side) uint16 12-bit frames: low-frequency noise that drifts over time."""
    rng = np.random.default_rng(seed)
    coarse = rng.random((FRAMES // 8 + 2, side // 16 + 2, side // 16 + 2))
    t = np.linspace(0, coarse.shape[0] - 1.001, FRAMES)
    lo = np.floor(t).astype(int)
    frac = (t - lo)[:, None, None]
    cells = coarse[lo] * (1 - frac) + coarse[lo + 1] * frac
    big = np.kron(cells, np.ones((16, 16)))[:, :side, :side]
    return np.clip(big * 4095 + rng.normal(0, 20, big.shape), 0, 4095).astype(np.uint16)


def encode_pipe(frames: np.ndarray, qp: int, preset: str, tmp: str) -> bytes:
    """The packager's encode by the ffmpeg binary: raw frames on stdin, a fragmented MP4 out."""
    e, h, w = frames.shape
    path = os.path.join(tmp, "pipe.mp4")
    rate = f"{TIMING.rate.numerator}/{TIMING.rate.denominator}"
    subprocess.run(["ffmpeg", "-v", "error", "-nostdin", "-threads", "1", "-f", "rawvideo", "-pix_fmt", PIXEL_FORMAT,
                    "-s", f"{w}x{h}", "-framerate", rate, "-i", "pipe:", "-c:v", "libx265", "-pix_fmt", PIXEL_FORMAT,
                    "-preset", preset, "-x265-params", x265_params(qp, e), "-tag:v", "hvc1",
                    "-movflags", "+frag_keyframe+empty_moov+default_base_moof", "-fflags", "+bitexact",
                    "-video_track_timescale", str(TIMING.timescale), "-y", path],
                   input=frames.astype("<u2").tobytes(), check=True)
    with open(path, "rb") as f:
        return f.read()


def decode_pipe(data: bytes, side: int, tmp: str) -> tuple[float, float, np.ndarray]:
    path = os.path.join(tmp, "decode.mp4")
    with open(path, "wb") as f:
        f.write(data)
    frame_bytes = side * side * 2
    start = time.perf_counter()
    first = 0.0
    out = []
    proc = subprocess.Popen(["ffmpeg", "-v", "error", "-nostdin", "-i", path, "-f", "rawvideo", "-pix_fmt",
                             PIXEL_FORMAT, "-fps_mode", "passthrough", "pipe:"], stdout=subprocess.PIPE)
    while len(chunk := proc.stdout.read(frame_bytes)) == frame_bytes:
        if not out:
            first = time.perf_counter() - start
        out.append(np.frombuffer(chunk, "<u2").reshape(side, side))
    proc.wait()
    return first, time.perf_counter() - start, np.stack(out)


def decode_pyav(data: bytes, side: int, tmp: str) -> tuple[float, float, np.ndarray]:
    start = time.perf_counter()
    first = 0.0
    out = []
    for frame in iter_frames(data, FRAMES, side, side):
        if not out:
            first = time.perf_counter() - start
        out.append(frame)
    return first, time.perf_counter() - start, np.stack(out)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return 10 * np.log10(4095.0**2 / max(mse, 1e-12))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--qp", type=int, default=20)
    parser.add_argument("--preset", default="medium")
    args = parser.parse_args()
    if shutil.which("ffmpeg") is None:
        raise SystemExit("the ffmpeg binary is not on PATH (Debian: apt-get install ffmpeg)")
    encodes, decodes = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for side in args.sides:
            frames = smooth_frames(side)
            enc_routes = {"PyAV (project)": lambda f: encode_gop(f, args.qp, TIMING, args.preset),
                          "ffmpeg pipe": lambda f: encode_pipe(f, args.qp, args.preset, tmp)}
            times: dict[str, list[float]] = {name: [] for name in enc_routes}
            data: dict[str, bytes] = {}
            for r in range(args.rounds):
                for name in enc_routes if r % 2 == 0 else list(enc_routes)[::-1]:
                    start = time.perf_counter()
                    data[name] = enc_routes[name](frames)
                    times[name].append(time.perf_counter() - start)
            for name in enc_routes:
                _, _, decoded = decode_pyav(data[name], side, tmp)
                encodes.append((side, name, statistics.median(times[name]), len(data[name]), psnr(decoded, frames)))
                print(f"side {side}: encode {name} {encodes[-1][2]:.2f} s, {len(data[name]) / 1024:.0f} KB, "
                      f"{encodes[-1][4]:.2f} dB", flush=True)
            segment = data["PyAV (project)"]
            dec_routes = {"PyAV (project)": decode_pyav, "ffmpeg pipe": decode_pipe}
            runs: dict[str, list[tuple[float, float]]] = {name: [] for name in dec_routes}
            decoded = {}
            for r in range(args.rounds):
                for name in dec_routes if r % 2 == 0 else list(dec_routes)[::-1]:
                    first, total, decoded[name] = dec_routes[name](segment, side, tmp)
                    runs[name].append((first, total))
            if not np.array_equal(decoded["ffmpeg pipe"], decoded["PyAV (project)"]):
                raise SystemExit(f"side {side}: the two routes decode different frames")
            for name, timing in runs.items():
                decodes.append((side, len(segment), name, statistics.median(f for f, _ in timing),
                                statistics.median(t for _, t in timing)))
                print(f"side {side}: decode {name} first frame {decodes[-1][3] * 1e3:.1f} ms, all {FRAMES} "
                      f"{decodes[-1][4] * 1e3:.0f} ms", flush=True)
    print(f"\n| grid side | route | encode s (QP {args.qp}, {args.preset}) | segment KB | PSNR dB |")
    print("|---|---|---|---|---|")
    for side, name, seconds, size, db in encodes:
        print(f"| {side} | {name} | {seconds:.2f} | {size / 1024:.0f} | {db:.2f} |")
    print(f"\n| grid side | segment KB | route | first frame ms | all {FRAMES} frames ms | ms per frame |")
    print("|---|---|---|---|---|---|")
    for side, size, name, first, total in decodes:
        print(f"| {side} | {size / 1024:.0f} | {name} | {first * 1e3:.1f} | {total * 1e3:.0f} | "
              f"{total * 1e3 / FRAMES:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
