"""Pinhole cameras in the OpenCV convention (x right, y down, z forward)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from stgs.errors import StgsError
from stgs.limits import MAX_IMAGE_SIDE, MAX_PATH_CAMERAS
from stgs.tree import CAMERAS, CAMERAS_FORMAT


@dataclass
class Camera:
    """One calibrated view."""

    name: str
    """Identifier (file-name safe)."""
    K: torch.Tensor
    """(3, 3) intrinsics, float64."""
    viewmat: torch.Tensor
    """(4, 4) world-to-camera, float64."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, (3,)."""
        rot, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -rot.T @ t

    def to_json(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height,
                "K": self.K.tolist(), "viewmat": self.viewmat.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> Camera:
        K = torch.tensor(d["K"], dtype=torch.float64)
        viewmat = torch.tensor(d["viewmat"], dtype=torch.float64)
        name = d.get("name")
        if K.shape != (3, 3) or viewmat.shape != (4, 4):
            raise ValueError(f"camera {name!r}: K must be 3x3 and viewmat 4x4")
        if not (torch.isfinite(K).all() and torch.isfinite(viewmat).all()):
            raise ValueError(f"camera {name!r}: K and viewmat must be finite numbers")
        if not (K[0, 0] > 0 and K[1, 1] > 0) or K[2].tolist() != [0.0, 0.0, 1.0]:
            raise ValueError(f"camera {name!r}: K needs positive focal lengths and a last row of 0 0 1")
        if viewmat[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
            raise ValueError(f"camera {name!r}: viewmat's last row must be 0 0 0 1")
        return cls(str(d["name"]), K, viewmat, int(d["width"]), int(d["height"]))


def resize(cam: Camera, width: int, height: int) -> Camera:
    """The same view at another image size (intrinsics scaled per axis)."""
    if (width, height) == (cam.width, cam.height):
        return cam
    K = cam.K.clone()
    K[0] *= width / cam.width
    K[1] *= height / cam.height
    return Camera(cam.name, K, cam.viewmat, width, height)


def intrinsics(width: int, height: int, fov_x_deg: float) -> torch.Tensor:
    """K for a centred principal point and a horizontal field of view."""
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)


def look_at(eye, target, world_up=(0.0, 1.0, 0.0)) -> torch.Tensor:
    """World-to-camera 4x4 of a camera at eye looking at target (world y up)."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    up = torch.as_tensor(world_up, dtype=torch.float64)
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def orbit(count: int, radius: float, height: float, target=(0.0, 0.0, 0.0), width: int = 320,
          height_px: int = 240, fov_x_deg: float = 60.0, phase_deg: float = 0.0,
          prefix: str = "orbit") -> list[Camera]:
    """`count` cameras evenly spaced on a horizontal circle, all looking at target."""
    K = intrinsics(width, height_px, fov_x_deg)
    cams = []
    for i in range(count):
        angle = math.radians(phase_deg) + 2 * math.pi * i / count
        eye = (target[0] + radius * math.sin(angle), height, target[2] + radius * math.cos(angle))
        cams.append(Camera(f"{prefix}{i:02d}", K.clone(), look_at(eye, target), width, height_px))
    return cams


def rig_focus(cameras: list[Camera]) -> tuple[torch.Tensor, float]:
    """The point nearest every optical axis, and the cameras' mean distance from it."""
    centres = torch.stack([c.center for c in cameras])
    axes = torch.stack([c.viewmat[2, :3] for c in cameras])  # viewing directions (world)
    eye = torch.eye(3, dtype=torch.float64)
    A = sum(eye - a[:, None] @ a[None] for a in axes)
    b = sum((eye - a[:, None] @ a[None]) @ c for a, c in zip(axes, centres, strict=True))
    focus = torch.linalg.lstsq(A, b[:, None]).solution[:, 0]
    return focus, float((centres - focus).norm(dim=1).mean())


def rig_size(cams: list[Camera]) -> float:
    """1.1 × the largest distance of a camera centre from their mean: the rig's size, which sets the trainer's
    unit of length (stgs.data.units); 0 where the cameras stand at one point."""
    centres = torch.stack([c.center for c in cams])
    return float((centres - centres.mean(0)).norm(dim=1).max()) * 1.1


def scene_extent(cams: list[Camera]) -> float:
    """rig_size + 1e-6 (never 0): what the trainer's position learning rate is scaled by (as 3DGS's
    cameras_extent)."""
    return rig_size(cams) + 1e-6


def rig_down(cameras: list[Camera]) -> torch.Tensor:
    """The rig's down direction: the unit mean of the cameras' image-down axes (world, float64)."""
    down = torch.stack([c.viewmat[1, :3] for c in cameras]).double().mean(0)
    return down / down.norm().clamp_min(1e-12)


def surrounds(cameras: list[Camera]) -> bool:
    """Whether the cameras stand around the scene looking in (a dome or ring), not side by side looking out
    at it (a forward-facing rig)."""
    focus, _ = rig_focus(cameras)
    directions = torch.stack([c.center for c in cameras]).double() - focus
    directions /= directions.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return float(directions.mean(0).norm()) < 0.8


def rig_orbit(cameras: list[Camera], count: int, width: int, height: int, fov_x_deg: float = 60.0,
              shrink: float = 0.8) -> list[Camera]:
    """`count` cameras on a circle inside a rig that surrounds the scene: around the axis through the rig focus
    along the cameras' mean image-up direction, at their mean height, `shrink` x their mean distance from
    that axis, all looking at the focus (inside whatever walls the rig captured)."""
    focus, _ = rig_focus(cameras)
    up = -rig_down(cameras)
    offsets = torch.stack([c.center for c in cameras]).double() - focus
    along = offsets @ up
    radial = offsets - along[:, None] * up
    radius = shrink * float(radial.norm(dim=1).mean())
    first = radial[0] / radial[0].norm().clamp_min(1e-12)
    second = torch.linalg.cross(up, first)
    lift = float(along.mean()) * up
    K = intrinsics(width, height, fov_x_deg)
    out = []
    for i in range(count):
        angle = 2 * math.pi * i / count
        eye = focus + lift + radius * (math.cos(angle) * first + math.sin(angle) * second)
        out.append(Camera(f"orbit{i:02d}", K.clone(), look_at(eye.tolist(), focus.tolist(), up.tolist()),
                          width, height))
    return out


def parse_scene_cameras(doc: object) -> list[Camera]:
    """Cameras of a cameras.json document (from the network: checked, never trusted)."""
    if not isinstance(doc, dict) or doc.get("format") != CAMERAS_FORMAT or not isinstance(doc.get("cameras"), list):
        raise StgsError(f"cameras.json is not a {CAMERAS_FORMAT} document")
    return checked_cameras(doc["cameras"], CAMERAS)


def read_scene_cameras(folder: Path) -> list[Camera]:
    """The cameras of the cameras.json in a model dir or packaged tree."""
    path = Path(folder) / CAMERAS
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StgsError(f"{path}: cannot read the scene's cameras ({exc})") from None
    return parse_scene_cameras(doc)


def checked_cameras(items: list, where: str) -> list[Camera]:
    """Cameras (Camera.to_json items) from outside: each well-formed and of an image size within the limits."""
    if len(items) > MAX_PATH_CAMERAS:
        raise StgsError(f"{where}: more than {MAX_PATH_CAMERAS} cameras")
    cameras = []
    for i, item in enumerate(items):
        try:
            cam = Camera.from_json(item)
        except (KeyError, TypeError, ValueError) as exc:
            raise StgsError(f"{where}: camera {i} is malformed ({exc})") from None
        if not (1 <= cam.width <= MAX_IMAGE_SIDE and 1 <= cam.height <= MAX_IMAGE_SIDE):
            raise StgsError(f"{where}: camera {cam.name!r} has image size {cam.width}x{cam.height}")
        cameras.append(cam)
    return cameras
