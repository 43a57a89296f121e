"""`stgs inspect`: what a capture holds, before anything trains on it (docs/CAPTURE.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from stgs.cli.args import name_list, positive_float


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
             f"  frames: {report['frames']} at {report['fps']:g} fps ({report['seconds']:.2f} s)",
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
