"""Rig geometry (stgs.camera) and the player's default orbit built from it."""

from __future__ import annotations

import json
import math

import pytest
import torch

from stgs.camera import Camera, intrinsics, look_at, read_scene_cameras, rig_focus, rig_orbit, surrounds
from stgs.client.config import ViewSpec
from stgs.client.viewpoint import build_trajectory
from stgs.errors import StgsError
from stgs.model.gop import GOPModel, GOPShape
from stgs.tree import CAMERAS, CAMERAS_FORMAT

FOCUS = (0.0, -1.0, 0.0)


def dome(count: int = 10) -> list[Camera]:
    """Cameras on a ring of radius 3 at y = -3 (world y points down, as in Panoptic), looking at FOCUS."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count + 0.3
        eye = (3 * math.cos(a), -3.0, 3 * math.sin(a))
        cams.append(Camera(f"d{i}", intrinsics(64, 48, 60.0), look_at(eye, FOCUS, (0.0, -1.0, 0.0)), 64, 48))
    return cams


def test_rig_orbit_circles_inside_the_rig_looking_at_its_focus():
    cams = dome()
    focus, _ = rig_focus(cams)
    assert torch.allclose(focus, torch.tensor(FOCUS, dtype=torch.float64), atol=1e-9)
    orbit = rig_orbit(cams, 8, 80, 60)
    assert len(orbit) == 8 and all((c.width, c.height) == (80, 60) for c in orbit)
    centres = torch.stack([c.center for c in orbit])
    assert torch.allclose(centres[:, 1], torch.tensor(-3.0, dtype=torch.float64), atol=1e-9)  # the rig's height
    radial = torch.stack([centres[:, 0], centres[:, 2]], 1).norm(dim=1)
    assert torch.allclose(radial, torch.tensor(0.8 * 3.0, dtype=torch.float64), atol=1e-9)  # inside the ring
    for cam in orbit:
        p = cam.viewmat[:3, :3] @ torch.tensor(FOCUS, dtype=torch.float64) + cam.viewmat[:3, 3]
        assert abs(p[0]) < 1e-9 and abs(p[1]) < 1e-9 and p[2] > 0  # the focus at the image centre
        assert cam.viewmat[1, 1] > 0  # image down is world +y here: upright


def test_the_default_orbit_follows_a_surrounding_rig_only():
    model = GOPModel(GOPShape(16, gop_size=4))
    with torch.no_grad():
        model.xyz.normal_(0, 20.0)  # Gaussians far out, like walls: a framing orbit would sit outside them
        model.opacity_logit.fill_(2.0)
    spec = ViewSpec()
    inside = build_trajectory(spec, dome(), model, 6).cameras
    assert max(float(c.center.norm()) for c in inside) < 4.0
    forward = [Camera(f"f{i}", intrinsics(64, 48, 60.0), look_at((x, 0.0, -4.0), (0.0, 0.0, 0.0)), 64, 48)
               for i, x in enumerate((-1.0, 0.0, 1.0))]
    assert not surrounds(forward)
    framing = build_trajectory(spec, forward, model, 6).cameras
    assert min(float(c.center.norm()) for c in framing) > 10.0


def test_read_scene_cameras_reads_a_dir_and_names_the_file_when_it_cannot(tmp_path):
    cam = dome(1)[0]
    (tmp_path / CAMERAS).write_text(json.dumps({"format": CAMERAS_FORMAT, "version": 1, "cameras": [cam.to_json()]}))
    assert [c.name for c in read_scene_cameras(tmp_path)] == ["d0"]
    (tmp_path / CAMERAS).write_text("{not json")
    with pytest.raises(StgsError, match=r"cameras\.json: cannot read"):
        read_scene_cameras(tmp_path)
    with pytest.raises(StgsError, match=r"cameras\.json: cannot read"):
        read_scene_cameras(tmp_path / "missing")
    (tmp_path / CAMERAS).write_text(json.dumps({"format": "other", "cameras": []}))
    with pytest.raises(StgsError, match="not a streamstgs-cameras document"):
        read_scene_cameras(tmp_path)
