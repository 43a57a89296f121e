"""`stgs inspect DATASET`: what `--kind auto` finds in a capture, its cameras and frames, the rig's size and
centre, the held-out cameras and any problem, as one report; and a picture of the rig from above."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera, rig_down, rig_focus
from stgs.data import detect_kind, open_dataset, split
from stgs.data.distortion import Intrinsics
from stgs.errors import StgsError


def _intrinsics(ds, camera: Camera) -> dict:
    """The camera's calibration as the capture gives it (lens model and distortion where the reader has them)."""
    get = getattr(ds, "intrinsics", None)
    if get is not None:
        return get(camera.name).to_json()
    return Intrinsics.pinhole_of(camera).to_json()


def inspect_dataset(path: Path, kind: str = "auto", holdout: list[str] | None = None,
                    check_frames: bool = True, fps: float | None = None) -> dict:
    """A report of the capture at `path` (StgsError where it cannot be opened at all); problems that leave it
    readable are listed under "problems"."""
    path = Path(path)
    found = detect_kind(path) if kind == "auto" else kind
    ds = open_dataset(path, kind, fps=fps)
    cams = ds.cameras(0)
    problems: list[str] = []
    focus, radius = rig_focus(cams) if len(cams) >= 2 else (cams[0].center, 0.0)
    centres = torch.stack([c.center for c in cams])
    cameras = []
    for cam in cams:
        entry = {"name": cam.name} | _intrinsics(ds, cam)
        entry["centre"] = [float(v) for v in cam.center]
        cameras.append(entry)
    sizes = {(c.width, c.height) for c in cams}
    distorted = [c["name"] for c in cameras if any(c["coefficients"])]
    try:
        train, val = split(ds, holdout)
    except StgsError as exc:
        problems.append(str(exc))
        train, val = list(ds.camera_names), []
    if len(train) < 3:
        problems.append(f"{len(train)} training camera(s): triangulation and training need at least 3")
    if check_frames:
        try:
            ds.check_views(list(range(ds.num_frames)), list(ds.camera_names))
        except StgsError as exc:
            problems.append(str(exc))
    points = ds.points(0)
    last = ds.cameras(ds.num_frames - 1)
    moves = any(not (torch.equal(a.K, b.K) and torch.equal(a.viewmat, b.viewmat)) for a, b in zip(cams, last,
                                                                                                    strict=True))
    return {
        "path": str(path), "kind": found, "name": ds.name, "frames": ds.num_frames, "fps": ds.fps,
        "seconds": ds.num_frames / ds.fps, "cameras": cameras, "camera_count": len(cams),
        "resolutions": sorted(f"{w}x{h}" for w, h in sizes), "distorted_cameras": distorted,
        "calibration": "changes between frames" if moves else "the same for every frame",
        "rig": {"centre": [float(v) for v in focus], "radius": radius,
                "span": float((centres.max(0).values - centres.min(0).values).norm()),
                "up": [float(v) for v in -rig_down(cams)]},
        "holdout": val, "training_cameras": train, "seed_points": 0 if points is None else len(points[0]),
        "problems": problems,
    }


def plot_rig(report: dict, cameras: list[Camera], out: Path) -> None:
    """The rig seen from above (along its up axis): each camera's centre, frustum and name, the rig's centre;
    written to `out` (PNG, atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    up = np.array(report["rig"]["up"])
    # A right-handed frame on the ground plane: two axes orthogonal to up.
    helper = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 0, 1.0])
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    ground = lambda p: (float(np.dot(p, a)), float(np.dot(p, b)))  # noqa: E731
    depth = 0.25 * (report["rig"]["radius"] or 1.0)
    fig, ax = plt.subplots(figsize=(7, 7))
    for cam in cameras:
        rot = cam.viewmat[:3, :3].double().numpy()
        centre = cam.center.double().numpy()
        K = cam.K.double().numpy()
        corners = []
        for u, v in ((0, 0), (cam.width, 0), (cam.width, cam.height), (0, cam.height)):
            ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0]) * depth
            corners.append(centre + rot.T @ ray)
        c = ground(centre)
        for corner in corners:
            ax.plot([c[0], ground(corner)[0]], [c[1], ground(corner)[1]], color="tab:blue", lw=0.6)
        ring = [ground(p) for p in corners + corners[:1]]
        ax.plot([p[0] for p in ring], [p[1] for p in ring], color="tab:blue", lw=0.6)
        colour = "tab:red" if cam.name in report["holdout"] else "black"
        ax.plot(*c, "o", color=colour, ms=3)
        ax.annotate(cam.name, c, fontsize=7, color=colour, xytext=(3, 3), textcoords="offset points")
    ax.plot(*ground(np.array(report["rig"]["centre"])), "+", color="tab:green", ms=12)
    ax.set_aspect("equal")
    ax.set_title(f"{report['name']}: {report['camera_count']} cameras from above (held out in red)")
    out = Path(out)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".png", dir=out.parent if str(out.parent) else ".")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=120)
        os.replace(tmp, out)
    finally:
        plt.close(fig)
        Path(tmp).unlink(missing_ok=True)
