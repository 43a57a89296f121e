"""`stgs inspect`: what a capture holds, before anything trains on it (docs/CAPTURE.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from stgs.cli.args import UsageError, name_list, positive_float, positive_int, positive_seconds, seconds


def add_inspect(sub: argparse._SubParsersAction) -> None:
    from stgs.data import KINDS

    p = sub.add_parser("inspect", help="describe a capture: layout, cameras, frames, rig, held-out cameras, problems",
                       description="Report what --kind auto finds in a capture (or the layout --kind names): the "
                       "cameras (resolution, intrinsics, distortion), frames and frame rate, the rig's size and "
                       "centre, the held-out cameras and any problem (docs/CAPTURE.md).")
    p.add_argument("dataset", type=Path, help="the capture's folder (or its transforms.json)")
    p.add_argument("--kind", choices=["auto", *KINDS], default="auto", help="dataset layout (default: auto)")
    p.add_argument("--holdout", type=name_list, help="comma-separated validation cameras (default: the dataset's)")
    p.add_argument("--fps", type=positive_float,
                   help="frame rate of a capture of image files, which do not say theirs (default 30)")
    p.add_argument("--plot", type=Path, metavar="PNG", help="also draw the rig from above, each camera's frustum")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--no-check", dest="check", action="store_false",
                   help="skip checking every frame's image header (large captures)")
    p.set_defaults(run=run_inspect)


def describe(report: dict) -> str:
    """The report as a person reads it."""
    rig = report["rig"]
    lines = [f"{report['path']}: {report['kind']} ({report['name']})",
             f"  frames: {report['frames']} at {report['fps']:g} fps ({report['seconds']:.2f} s)"
             + (": a still scene (stgs train --layers still)" if report["frames"] == 1 else ""),
             f"  cameras: {report['camera_count']} ({', '.join(report['resolutions'])}), calibration "
             f"{report['calibration']}",
             f"  rig: centre ({', '.join(f'{v:.3g}' for v in rig['centre'])}), radius {rig['radius']:.3g}, span "
             f"{rig['span']:.3g}, up ({', '.join(f'{v:.2f}' for v in rig['up'])})",
             f"  held out: {', '.join(report['holdout']) or 'none'}; seed points from the capture: "
             f"{report['seed_points'] or 'none (triangulated)'}"]
    for cam in report["cameras"]:
        distortion = (" " + ", ".join(f"{v:.4g}" for v in cam["coefficients"])) if any(cam["coefficients"]) else ""
        lines.append(f"  {cam['name']:>12}: {cam['width']}x{cam['height']} {cam['model']}{distortion}, "
                     f"f ({cam['fx']:.1f}, {cam['fy']:.1f}), c ({cam['cx']:.1f}, {cam['cy']:.1f})")
    if report["distorted_cameras"]:
        lines.append(f"  undistorted once into the frame cache: {', '.join(report['distorted_cameras'])}")
    lines += [f"  problem: {p}" for p in report["problems"]] or ["  no problems found"]
    return "\n".join(lines)


def run_inspect(args: argparse.Namespace) -> int:
    from stgs.data import open_dataset
    from stgs.data.inspect import inspect_dataset, plot_rig

    report = inspect_dataset(args.dataset, args.kind, args.holdout, args.check, args.fps)
    if args.plot is not None:
        plot_rig(report, open_dataset(args.dataset, args.kind, fps=args.fps).cameras(0), args.plot)
    print(json.dumps(report, indent=1) if args.json else describe(report))
    if args.plot is not None and not args.json:
        print(f"wrote {args.plot}")
    return 1 if report["problems"] else 0


def add_prepare(sub: argparse._SubParsersAction) -> None:
    from stgs.prepare.settings import (
        CAMERA_MODELS,
        DEFAULT_CALIB_FRAMES,
        DEFAULT_CAMERA_MODEL,
        LAYOUTS,
        RIG_RADIUS,
        SYNC_METHODS,
    )

    p = sub.add_parser("prepare", help="turn one video per camera into a synchronised, calibrated capture",
                       description="Check the footage, synchronise it (audio, frame index or given offsets), "
                       "calibrate the rig with COLMAP (pycolmap) on a few frames, and write every frame of the "
                       "common span undistorted, with prepare_report.json (docs/CAPTURE.md, 'Preparing raw "
                       "footage'). The output trains with `stgs train OUT`.")
    p.add_argument("inputs", type=Path, nargs="+", metavar="VIDEO",
                   help="one video per camera (named by the file's stem), or a folder of them; the last path is OUT")
    p.add_argument("--layout", choices=LAYOUTS, default="frames",
                   help="frames: frameNNNNNN/images/<cam>.png; videos: one lossless FFV1 video per camera, "
                   "smaller on disk (default: frames)")
    p.add_argument("--sync", choices=SYNC_METHODS, default="auto",
                   help="auto: by audio where every video has an audio track, else by frame index (default)")
    p.add_argument("--offsets", metavar="CAM=FRAMES,...",
                   help="frames each named camera started after the first; these override the audio's")
    p.add_argument("--calib-frames", type=positive_int, default=DEFAULT_CALIB_FRAMES,
                   help=f"frames spread over the span that the rig is calibrated on (default {DEFAULT_CALIB_FRAMES})")
    p.add_argument("--camera-model", choices=CAMERA_MODELS, default=DEFAULT_CAMERA_MODEL,
                   help=f"COLMAP lens model fitted per camera (default {DEFAULT_CAMERA_MODEL})")
    p.add_argument("--intrinsics", type=Path, metavar="FILE",
                   help='known lenses, kept as they are: {"lens": {...}} for every camera, {"cameras": {name: '
                   '{...}}} for some, or an earlier prepare_report.json (docs/CAPTURE.md, "Known lenses")')
    p.add_argument("--start", type=seconds, default=0.0, help="seconds into the common span to begin at")
    p.add_argument("--seconds", type=positive_seconds, help="length to keep (default: to the end of the span)")
    p.add_argument("--rig-radius", type=positive_float, default=RIG_RADIUS,
                   help=f"mean distance of the cameras from their centroid in the output (default {RIG_RADIUS})")
    p.add_argument("--resume", action="store_true", help="continue a run that was killed")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_prepare)


def describe_prepare(report: dict, out: Path) -> str:
    """The prepare report as a person reads it."""
    cal, span = report["calibration"], report["span"]
    offsets = ", ".join(f"{o['camera']} {o['frames']:+d}" + (f" (peak/side {o['confidence']:.1f})"
                                                            if o["confidence"] is not None else "")
                        for o in report["sync"]["offsets"])
    lines = [f"{out}: {len(report['footage'])} cameras at {report['fps']:g} fps, layout {report['layout']}",
             f"  sync ({', '.join(report['sync']['sources']) or 'reference only'}): {offsets}",
             f"  span: {span['frames']} frames ({span['seconds']:.2f} s) from reference frame {span['start']}",
             f"  calibration: {cal['registered']} of {cal['total']} cameras registered on frames {cal['frames']}, "
             f"mean reprojection error {cal['mean_reprojection_error_px']:.3f} px, {cal['points']} points, "
             f"{cal['seconds']:.1f} s",
             "  tracks per camera: " + ", ".join(f"{k} {v}" for k, v in cal["tracks"].items()),
             f"  lenses: {sum(v == 'given' for v in cal['lenses'].values())} given, "
             f"{sum(v == 'fitted' for v in cal['lenses'].values())} fitted ({cal['camera_model']})",
             f"  wrote {report['capture_bytes'] / 1e6:.1f} MB in {report['timings']['frames_s']:.1f} s; "
             f"train it with: stgs train {out} MODEL_DIR"]
    return "\n".join(lines)


def run_prepare(args: argparse.Namespace) -> int:
    from stgs.prepare.run import PrepareConfig, prepare
    from stgs.prepare.sync import parse_offsets

    if len(args.inputs) < 2:
        raise UsageError("give the videos (or a folder of them) and then OUT")
    try:
        offsets = parse_offsets(args.offsets or "")
    except ValueError as exc:
        raise UsageError(f"--offsets: {exc}") from None
    *videos, out = args.inputs
    config = PrepareConfig(videos=videos, out=out, layout=args.layout, sync=args.sync, offsets=offsets,
                           calib_frames=args.calib_frames, camera_model=args.camera_model,
                           intrinsics=args.intrinsics, start=args.start,
                           seconds=args.seconds, rig_radius=args.rig_radius, resume=args.resume,
                           progress=not args.quiet)
    report = prepare(config)
    print(json.dumps(report, indent=1) if args.json else describe_prepare(report, out))
    return 0
