"""`stgs export`: frames of a scene as 3DGS files (PLY, SPZ, glTF KHR_gaussian_splatting) for other tools."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stgs.cli.args import UsageError, vector3

FORMAT_NAMES = ("ply", "spz", "glb")


def add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write frames of a scene as 3DGS PLY, SPZ or glTF (KHR_gaussian_splatting)",
                       description="Write the Gaussians of a frame (static layer and deformed dynamic layer) of a "
                       "model dir or packaged tree in a format other splat tools read (docs/INTEROP.md).")
    p.add_argument("source", type=Path, help="model dir, or packaged tree (its folder or manifest.mpd)")
    p.add_argument("out", type=Path, help="output file (.ply, .spz, .glb); with --frames, a folder")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--frame", type=int, default=0, help="the frame to write (default 0)")
    what.add_argument("--frames", metavar="A:B",
                      help="write frames A..B-1 (either side may be left out), one file each and sequence.json")
    p.add_argument("--format", choices=FORMAT_NAMES, help="file format (default: OUT's suffix; with --frames, ply)")
    p.add_argument("--rep", help="packaged tree: the Representation decoded (default: the highest bandwidth)")
    eye = p.add_mutually_exclusive_group()
    eye.add_argument("--camera", help="evaluate the view-dependent parts from this scene camera (default: the first)")
    eye.add_argument("--eye", type=vector3, metavar="X,Y,Z", help="evaluate them from this point instead")
    p.add_argument("--sh-degree", type=int, choices=[0, 1], default=0,
                   help="0 (default): colours as the eye sees them; 1: a degree-1 colour fitted over the scene's "
                   "cameras (and the static layer's own)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run_export)


def scene_cameras(source: Path):
    """The scene's cameras: cameras.json beside the model dir or tree, or a synth model dir's ground truth."""
    from stgs.camera import read_scene_cameras
    from stgs.data import open_dataset
    from stgs.errors import StgsError

    folder = source.parent if source.is_file() else source
    try:
        return read_scene_cameras(folder)
    except StgsError:
        pass
    try:
        return open_dataset(folder, "synth").cameras(0)
    except (StgsError, OSError, ValueError):
        return None


def run_export(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    from stgs.interop.files import format_of, write_sequence, write_splats
    from stgs.interop.frames import frame_splats, open_source, parse_frames

    fmt = format_of(args.out, args.format) if args.frames is None else args.format or "ply"
    source = open_source(args.source, args.rep)
    cameras = scene_cameras(args.source)
    if args.eye is not None:
        eye = torch.tensor(args.eye, dtype=torch.float64)
    elif cameras:
        named = {c.name: c for c in cameras}
        if args.camera is not None and args.camera not in named:
            raise UsageError(f"--camera {args.camera}: the scene's cameras are {', '.join(named)}")
        eye = named[args.camera or cameras[0].name].center
    else:
        raise UsageError("the scene has no cameras.json: give --eye X,Y,Z, the point its view-dependent parts are "
                         "evaluated from")
    centres = [c.center for c in cameras] if cameras else None

    def splats_of(frame: int):
        return frame_splats(source, frame, eye, args.sh_degree, centres)

    if args.frames is None:
        frame = parse_frames(str(args.frame), source.num_frames)[0]
        splats = splats_of(frame)
        size = write_splats(args.out, splats, fmt)
        print(f"wrote {args.out}: frame {frame} of {source.name}, {splats.count} Gaussians, {size} bytes")
        return 0
    frames = parse_frames(args.frames, source.num_frames)
    with tqdm(total=len(frames), desc="export", unit="frame", disable=args.quiet, file=sys.stderr) as bar:
        doc = write_sequence(args.out, frames, splats_of, fmt, source.fps, source.name, lambda _: bar.update())
    total = sum(r["bytes"] for r in doc["files"])
    print(f"wrote {args.out}: frames {frames[0]}-{frames[-1]} of {source.name} as {len(frames)} {fmt} files "
          f"({total} bytes) and sequence.json")
    return 0


def add_static_import(p: argparse.ArgumentParser, train: bool) -> None:
    """`--static-from` and its companions, on `stgs train` (train=True) and `stgs synth`."""
    p.add_argument("--static-from", type=Path, metavar="FILE",
                   help="a 3DGS file (.ply, .spz, .glb) made elsewhere as the scene's static layer (implies a layered "
                   "scene; SH above degree 1 folded, docs/INTEROP.md)")
    p.add_argument("--static-transform", type=Path, metavar="FILE",
                   help="with --static-from: the 4x4 similarity from the file's frame to the cameras' (JSON 4x4 "
                   "list, or 16 numbers; default: identity)")
    if train:
        p.add_argument("--static-cameras", type=Path, metavar="CAMERAS_JSON",
                       help="with --static-from: the 3DGS cameras.json it was trained with; the transform is fitted "
                       "from its camera centres to the dataset's cameras of the same names")
        p.add_argument("--static-refine", type=int, metavar="N",
                       help="with --static-from: fine-tune it for N iterations of stage A (default 0: used as it is)")


def static_import_overrides(args: argparse.Namespace) -> dict:
    """TrainConfig fields of the --static-* import flags (checked together here: the CLI's own vocabulary)."""
    if args.static_from is None:
        extra = [f for f in ("static_transform", "static_cameras", "static_refine") if getattr(args, f) is not None]
        if extra:
            raise UsageError(f"--{extra[0].replace('_', '-')} needs --static-from")
        return {}
    if args.layers == "single":
        raise UsageError("--static-from makes a layered scene (or a still): it does not go with --layers single")
    if args.static_transform is not None and args.static_cameras is not None:
        raise UsageError("--static-transform and --static-cameras both set the file's frame: give one")
    from stgs.interop.files import read_splats

    read_splats(args.static_from)  # a bad file is reported before anything is written
    # absolute: Ray tasks run elsewhere
    out: dict[str, object] = {"static_from": str(args.static_from.resolve()),
                              "layers": "still" if args.layers == "still" else "layered"}
    if args.static_transform is not None:
        from stgs.interop.static import read_transform

        out["static_transform"] = tuple(float(v) for v in read_transform(args.static_transform).reshape(-1))
    if args.static_cameras is not None:
        out["static_cameras"] = str(args.static_cameras.resolve())
    if args.static_refine is not None:
        out["static_refine"] = args.static_refine
    if args.static_grid_side is not None:
        out["static_import_side"] = args.static_grid_side
    return out


def describe_import(report: dict) -> str:
    """One line of how `stgs train` made its static layer of a file (stgs.interop.static.import_static's report)."""
    return (f"static layer from {report['file']}: {report['gaussians']} of its {report['file_gaussians']} Gaussians "
            f"on a grid of side {report['grid_side']} ({report['padded']} slots padded), SH {report['sh']}, transform "
            f"{report['transform_source']}")
