"""`stgs prepare`'s calibration on real footage: Panoptic basketball's 27 training cameras (../shared) written as
one lossless video per camera, calibrated with COLMAP on 1, 2, 3 and 5 frames, with the lenses fitted and with the
dataset's lenses given (`--intrinsics`); the time it takes and the camera error against the dataset's own
calibration, after a similarity fit (docs/BENCHMARKS.md, "Captures").

    .venv/bin/python -m bench.capture.prepare [--frames 150] [--counts 1,2,3,5] [--lenses fitted,given]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path

import av
import numpy as np

from stgs.data import open_dataset
from stgs.data.distortion import Intrinsics
from stgs.prepare.calibrate import calibrate, calibration_frames, rig_errors
from stgs.prepare.footage import probe, read_frames_at
from stgs.prepare.settings import CAMERA_MODELS, DEFAULT_CAMERA_MODEL

PANOPTIC = Path(__file__).resolve().parents[2] / "shared" / "data" / "panoptic-basketball"


def write_videos(folder: Path, frames: int) -> list[Path]:
    ds = open_dataset(PANOPTIC)
    paths = []
    for cam in ds.camera_names:
        path = folder / f"{cam}.mkv"
        with av.open(str(path), "w") as container:
            stream = container.add_stream("ffv1", rate=30)
            stream.width, stream.height, stream.pix_fmt = ds.width, ds.height, "bgr0"
            for f in range(frames):
                container.mux(stream.encode(av.VideoFrame.from_ndarray(ds.pixels(f, cam), format="rgb24")))
            container.mux(stream.encode())
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150, help="frames of footage per camera")
    parser.add_argument("--counts", default="1,2,3,5", help="calibration frame counts to measure")
    parser.add_argument("--camera-model", choices=CAMERA_MODELS, default=DEFAULT_CAMERA_MODEL,
                        help="COLMAP lens model")
    parser.add_argument("--lenses", default="fitted,given",
                        help="fitted (by COLMAP), given (the dataset's), or both")
    args = parser.parse_args(argv)
    if not PANOPTIC.is_dir():
        print(f"bench.capture.prepare: {PANOPTIC} is absent", file=sys.stderr)
        return 2
    cameras = open_dataset(PANOPTIC).cameras(0)
    truth = {c.name: c.viewmat.double().numpy() for c in cameras}
    given = {c.name: Intrinsics.pinhole_of(c) for c in cameras}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        footage = [probe(p) for p in write_videos(Path(tmp), args.frames)]
        for lenses, count in itertools.product(args.lenses.split(","), (int(c) for c in args.counts.split(","))):
            picks = calibration_frames(args.frames, count)
            views = {f.camera: read_frames_at(f, picks) for f in footage}
            t0 = time.perf_counter()
            try:
                cal = calibrate(views, args.camera_model, lenses=given if lenses == "given" else None)
            except Exception as exc:  # a count that does not calibrate is a row of the table too
                rows.append({"lenses": lenses, "calib_frames": count, "error": str(exc),
                             "seconds": time.perf_counter() - t0})
                print(json.dumps(rows[-1]), flush=True)
                continue
            seconds = time.perf_counter() - t0
            errors = rig_errors(cal.viewmats, truth)
            rot = np.array([e[0] for e in errors.values()])
            pos = np.array([e[1] for e in errors.values()])
            rows.append({"lenses": lenses, "calib_frames": count, "seconds": round(seconds, 1),
                         "registered": cal.report["registered"],
                         "total": cal.report["total"], "points": cal.report["points"],
                         "reprojection_px": round(cal.report["mean_reprojection_error_px"], 3),
                         "rotation_deg_median": round(float(np.median(rot)), 2),
                         "rotation_deg_max": round(float(rot.max()), 2),
                         "centre_pct_median": round(float(np.median(pos)), 2),
                         "centre_pct_max": round(float(pos.max()), 2),
                         "within_1deg_2pct": int(((rot <= 1) & (pos <= 2)).sum())})
            print(json.dumps(rows[-1]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
