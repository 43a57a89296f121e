"""One `stgs prepare` run: its config, and the stages driven in order, with `prepare_report.json` saying what
each found (docs/CAPTURE.md, "Preparing raw footage")."""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from stgs.data.distortion import Intrinsics
from stgs.errors import StgsError
from stgs.prepare.calibrate import Calibration, calibrate, calibration_frames, read_lenses
from stgs.prepare.footage import Footage, check_rates, find_videos, probe, read_frames, read_frames_at
from stgs.prepare.output import (
    REPORT,
    STATE,
    model_dir,
    read_state,
    staging_dir,
    write_frames,
    write_json,
    write_model,
    write_video,
)
from stgs.prepare.settings import DEFAULT_CALIB_FRAMES, DEFAULT_CAMERA_MODEL, LAYOUTS, RIG_RADIUS
from stgs.prepare.sync import common_span, find_offsets


@dataclass
class PrepareConfig:
    """One `stgs prepare` run."""

    videos: list[Path]
    """Video files, one per camera (a folder stands for the videos in it)."""
    out: Path
    """The capture folder to write (must not exist)."""
    layout: str = "frames"
    """"frames" (frameNNNNNN/images/<cam>.png) or "videos" (videos/<cam>.mkv, lossless)."""
    sync: str = "auto"
    """"auto" (audio where every video has it, else frame index), "audio" or "index"."""
    offsets: dict[str, int] = field(default_factory=dict)
    """Offsets in frames given by hand, by camera; they override the audio's."""
    calib_frames: int = DEFAULT_CALIB_FRAMES
    """Frames spread over the span that the rig is calibrated on."""
    camera_model: str = DEFAULT_CAMERA_MODEL
    """COLMAP's lens model fitted per camera."""
    intrinsics: Path | None = None
    """A JSON file of known lenses (stgs.prepare.calibrate.read_lenses): those cameras keep them."""
    start: float = 0.0
    """Seconds from the start of the common span where the capture begins."""
    seconds: float | None = None
    """Length of the capture in seconds (None: to the end of the common span)."""
    rig_radius: float = RIG_RADIUS
    """Mean distance of the prepared cameras from their centroid."""
    resume: bool = False
    """Continue a run that was killed (its staging folder beside `out`)."""
    progress: bool = True

    def validate(self) -> None:
        if self.layout not in LAYOUTS:
            raise StgsError(f"layout must be one of {', '.join(LAYOUTS)}, not {self.layout!r}")
        if self.calib_frames < 1:
            raise StgsError(f"calib_frames must be at least 1, not {self.calib_frames}")
        if not (self.rig_radius > 0 and np.isfinite(self.rig_radius)):
            raise StgsError(f"rig_radius must be a positive number, not {self.rig_radius}")


def _fingerprint(config: PrepareConfig, footage: list[Footage], span: dict, lenses: dict[str, Intrinsics]) -> dict:
    files = [{"path": str(f.path.resolve()), "bytes": f.path.stat().st_size,
              "mtime_ns": f.path.stat().st_mtime_ns} for f in footage]
    return {"videos": files, "span": span, "layout": config.layout, "calib_frames": config.calib_frames,
            "camera_model": config.camera_model, "rig_radius": config.rig_radius,
            "lenses": {k: v.to_json() for k, v in lenses.items()}}


def _calibration_json(cal: Calibration) -> dict:
    return {"intrinsics": {k: v.to_json() for k, v in cal.intrinsics.items()},
            "viewmats": {k: v.tolist() for k, v in cal.viewmats.items()},
            "points": cal.points.tolist(), "colours": cal.colours.tolist(), "report": cal.report}


def _calibration_from_json(d: dict) -> Calibration:
    return Calibration({k: Intrinsics.from_json(v) for k, v in d["intrinsics"].items()},
                       {k: np.array(v, dtype=np.float64) for k, v in d["viewmats"].items()},
                       np.array(d["points"], dtype=np.float64).reshape(-1, 3),
                       np.array(d["colours"], dtype=np.uint8).reshape(-1, 3), d["report"])


def _tree_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def prepare(config: PrepareConfig) -> dict:
    """Run every stage; returns the report (also written as `prepare_report.json` in the capture)."""
    config.validate()
    out = Path(config.out)
    if out.exists():
        raise StgsError(f"{out}: exists; prepare writes a new capture folder")
    stage = staging_dir(out)
    if stage.exists() and not config.resume:
        raise StgsError(f"{stage}: a run that did not finish left this; resume it (--resume) or remove it")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    footage = [probe(p) for p in find_videos([Path(v) for v in config.videos])]
    rate = check_rates(footage)
    offsets = find_offsets(footage, rate, config.sync, config.offsets)
    span = common_span(footage, offsets, rate, config.start, config.seconds)
    lenses = {}
    if config.intrinsics is not None:
        lenses = read_lenses(config.intrinsics, {f.camera: (f.width, f.height) for f in footage})
    timings["check_and_sync_s"] = time.perf_counter() - t0
    fingerprint = _fingerprint(config, footage, span.to_json(), lenses)
    state = read_state(stage) if config.resume else None
    if config.resume and state is None and stage.exists():
        shutil.rmtree(stage)  # killed before its first record: nothing in it can be trusted
    if state is not None and state.get("fingerprint") != fingerprint:
        raise StgsError(f"{stage}: it was started with other footage or settings; remove it to start again")
    cal_path = stage / "calibration.json"
    if state is not None and cal_path.is_file():
        cal = _calibration_from_json(json.loads(cal_path.read_text()))
    else:  # calibrated before anything is written: a rig that does not calibrate leaves nothing behind
        t1 = time.perf_counter()
        picks = calibration_frames(span.frames, config.calib_frames)
        views = {}
        for f in tqdm(footage, desc="calibration frames", unit="camera", disable=not config.progress):
            got = read_frames_at(f, [span.first_frame[f.camera] + i for i in picks])
            views[f.camera] = {i: got[span.first_frame[f.camera] + i] for i in picks}
        if config.progress:
            print(f"calibrating {len(footage)} cameras on {len(picks)} frame(s) with COLMAP", flush=True)
        cal = calibrate(views, config.camera_model, config.rig_radius, lenses=lenses)
        cal.report["frames"] = picks
        cal.report["seconds"] = round(time.perf_counter() - t1, 3)
    stage.mkdir(parents=True, exist_ok=True)
    if not cal_path.is_file():
        write_json(cal_path, _calibration_json(cal))
    if state is None:
        state = {"fingerprint": fingerprint, "done": {}}
        write_json(stage / STATE, state)
    timings["calibration_s"] = cal.report["seconds"]
    write_model(model_dir(stage, config.layout), cal.intrinsics, cal.viewmats, config.layout, cal.points,
                cal.colours)

    t2 = time.perf_counter()
    total = span.frames * len(footage)
    done_frames = sum(span.frames for f in footage if f.camera in state["done"])
    with tqdm(total=total, initial=done_frames, desc="frames", unit="view", disable=not config.progress) as bar:
        for f in footage:
            if f.camera in state["done"]:
                continue
            lens = cal.intrinsics[f.camera]
            frames = read_frames(f, span.first_frame[f.camera], span.frames)
            if config.layout == "frames":
                size = write_frames(stage, f.camera, frames, span.first_frame[f.camera], span.frames,
                                    lens.undistort, lambda: bar.update(1))
            else:
                size = write_video(stage, f.camera, frames, span.first_frame[f.camera], span.frames,
                                   lens.undistort, lambda: bar.update(1), rate)
            state["done"][f.camera] = size
            write_json(stage / STATE, state)
    timings["frames_s"] = time.perf_counter() - t2

    report = {
        "footage": [f.to_json() for f in footage],
        "fps": float(rate),
        "sync": {"sources": sorted({o.source for o in offsets[1:]}), "reference": offsets[0].camera,
                 "offsets": [o.to_json() for o in offsets]},
        "span": span.to_json(),
        "calibration": {**cal.report,
                        "intrinsics": {k: v.to_json() for k, v in cal.intrinsics.items()},
                        "undistorted_to": "PINHOLE (the same fx, fy, cx, cy)"},
        "layout": config.layout,
        "frames_bytes": int(sum(state["done"].values())),
        "timings": {k: round(v, 3) for k, v in timings.items()},
    }
    (stage / STATE).unlink()
    cal_path.unlink()
    report["capture_bytes"] = _tree_bytes(stage)  # the capture as it stays: the model and the frames
    write_json(stage / REPORT, report)
    os.replace(stage, out)
    return report
