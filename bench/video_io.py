#!/usr/bin/env python3
"""Feature-video decoding by the ffmpeg binary through a pipe (stgs.codec.video.iter_frames, what the project
uses) against PyAV in-process: the measurement behind choosing one route for encode and decode.

Per grid side, one GOP of E = 62 smooth 12-bit gray frames (the shape a PLAS-sorted feature video has) is
encoded once with the packager's settings (stgs.codec.video.encode_gop, QP 20, preset ultrafast to keep this
quick: the decoder's work barely depends on the preset); then each route decodes it `--rounds` times, order
alternating: time to the first frame (what a frame-by-frame player waits for at a GOP boundary) and to the
last. Both decoders run with their default threading and produce the same uint16 frames (checked).

PyAV is not a dependency of the project; install it in the venv to run this (`.venv/bin/pip install av`).

Usage: .venv/bin/python -m bench.video_io [--sides 256 512 1024] [--rounds 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import tempfile
import time

import numpy as np

from stgs.codec.video import VideoTiming, encode_gop, iter_frames

FRAMES = 62


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


def decode_pipe(path: str, side: int) -> tuple[float, float, np.ndarray]:
    start = time.perf_counter()
    first = 0.0
    out = []
    for frame in iter_frames(path, FRAMES, side, side):
        if not out:
            first = time.perf_counter() - start
        out.append(frame)
    return first, time.perf_counter() - start, np.stack(out)


def decode_pyav(path: str, side: int) -> tuple[float, float, np.ndarray]:
    import av

    start = time.perf_counter()
    first = 0.0
    out = []
    with av.open(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        for frame in container.decode(stream):
            if not out:
                first = time.perf_counter() - start
            out.append(frame.to_ndarray(format="gray12le"))
    return first, time.perf_counter() - start, np.stack(out)


ROUTES = {"ffmpeg pipe": decode_pipe, "PyAV": decode_pyav}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    if importlib.util.find_spec("av") is None:
        raise SystemExit("PyAV is not installed (.venv/bin/pip install av)")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for side in args.sides:
            frames = smooth_frames(side)
            data = encode_gop(frames, 20, VideoTiming.for_gop(FRAMES, 60, 30.0), preset="ultrafast")
            path = os.path.join(tmp, f"gop{side}.mp4")
            with open(path, "wb") as f:
                f.write(data)
            times: dict[str, list[tuple[float, float]]] = {name: [] for name in ROUTES}
            decoded = {}
            for r in range(args.rounds):
                for name in ROUTES if r % 2 == 0 else list(ROUTES)[::-1]:
                    first, total, decoded[name] = ROUTES[name](path, side)
                    times[name].append((first, total))
            if not np.array_equal(decoded["ffmpeg pipe"], decoded["PyAV"]):
                raise SystemExit(f"side {side}: the two routes decode different frames")
            for name, runs in times.items():
                rows.append((side, len(data), name, statistics.median(f for f, _ in runs),
                             statistics.median(t for _, t in runs)))
                print(f"side {side}: {name} first frame {rows[-1][3] * 1e3:.1f} ms, all {FRAMES} "
                      f"{rows[-1][4] * 1e3:.0f} ms", flush=True)
    print(f"\n| grid side | segment KB | route | first frame ms | all {FRAMES} frames ms | ms per frame |")
    print("|---|---|---|---|---|---|")
    for side, size, name, first, total in rows:
        print(f"| {side} | {size / 1024:.0f} | {name} | {first * 1e3:.1f} | {total * 1e3:.0f} | "
              f"{total * 1e3 / FRAMES:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
