"""Where the player looks from: a scene camera, an explicit pose, an orbit or a trajectory file."""

from __future__ import annotations

import json
from pathlib import Path

from stgs.camera import Camera, checked_cameras, intrinsics, look_at, resize, rig_orbit, surrounds
from stgs.client.config import ViewSpec
from stgs.errors import FieldError, StgsError
from stgs.model.gop import GOPModel
from stgs.model.renderer import framing_orbit
from stgs.model.static import StaticLayer


class Trajectory:
    """Presentation frame j (counted from the start of playback) -> camera."""

    def __init__(self, cameras: list[Camera]):
        if not cameras:
            raise StgsError("a trajectory needs at least one camera")
        self.cameras = cameras

    def camera(self, j: int) -> Camera:
        return self.cameras[j % len(self.cameras)]


def load_path_file(path: Path) -> list[Camera]:
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StgsError(f"{path}: cannot read the camera path ({exc})") from None
    items = doc.get("cameras") if isinstance(doc, dict) else doc
    if not isinstance(items, list):
        raise StgsError(f"{path}: a camera path is a JSON list of cameras or {{\"cameras\": [...]}}")
    return checked_cameras(items, str(path))


def build_trajectory(spec: ViewSpec, scene_cameras: list[Camera] | None, first_gop: GOPModel | StaticLayer,
                     frames_per_turn: int) -> Trajectory:
    """The trajectory `spec` asks for. The orbit circles inside the capture rig when the scene's cameras
    surround it (a trained capture has walls around the action), else frames the first GOP's Gaussians (a still
    scene's static layer)."""
    if spec.camera is not None:
        if not scene_cameras:
            raise FieldError("camera", "needs the scene's cameras.json beside the MPD, and this scene has none")
        by_name = {c.name: c for c in scene_cameras}
        if spec.camera not in by_name:
            raise StgsError(f"no camera {spec.camera!r} in this scene; it has {', '.join(by_name)}")
        cam = by_name[spec.camera]
        return Trajectory([resize(cam, *spec.size((cam.width, cam.height)))])
    if spec.eye is not None:
        w, h = spec.size()
        try:
            view = look_at(spec.eye, spec.target)
        except ValueError as exc:
            raise FieldError("eye", str(exc)) from None
        return Trajectory([Camera("pose", intrinsics(w, h, spec.fov_deg), view, w, h)])
    if spec.path != "orbit":
        return Trajectory(load_path_file(Path(spec.path)))
    w, h = spec.size()
    if scene_cameras and len(scene_cameras) >= 3 and surrounds(scene_cameras):
        return Trajectory(rig_orbit(scene_cameras, max(1, frames_per_turn), w, h, spec.fov_deg))
    return Trajectory(framing_orbit(first_gop, max(1, frames_per_turn), w, h, spec.fov_deg))
