"""A packaged scene's face in a catalogue: its title and description (scene.json) and its poster, one picture rendered
from the uncompressed model at the first scene camera and the middle of the first GOP (a still scene: its static
layer), as a WebP image."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from stgs.camera import Camera, resize
from stgs.errors import StgsError
from stgs.model.gop import GOPModel
from stgs.model.renderer import FrameRenderer, framing_orbit, render_still
from stgs.model.static import StaticLayer
from stgs.model.store import SceneMeta, load_gop
from stgs.packager.segments import scene_cameras
from stgs.tree import SCENE_FORMAT

POSTER_MAX_SIDE = 640
"""The poster's longer side at most (pixels): a catalogue card's picture, not a frame of the stream."""
POSTER_QUALITY = 85
"""WebP quality (0..100) of the poster."""


def poster_camera(model_dir: Path, gop: GOPModel | StaticLayer) -> Camera:
    """The first scene camera (scaled so that its longer side is at most POSTER_MAX_SIDE), or for a model with no
    cameras the first view of an orbit framing `gop` (the first GOP, or a still's static layer)."""
    cameras = scene_cameras(model_dir)
    if not cameras:
        return framing_orbit(gop, 1, POSTER_MAX_SIDE, POSTER_MAX_SIDE * 9 // 16)[0]
    cam = cameras[0]
    scale = min(1.0, POSTER_MAX_SIDE / max(cam.width, cam.height))
    return resize(cam, max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))


def render_poster(model_dir: Path, meta: SceneMeta, static: StaticLayer | None) -> tuple[np.ndarray, dict]:
    """(H, W, 3) uint8 RGB poster and where it was taken ({"camera", "frame"}): the middle frame of GOP 0, with the
    static layer where the scene has one; a still scene's static layer (frame 0)."""
    if meta.still:
        if static is None:
            raise StgsError(f"{model_dir}: a still scene needs its static layer")
        cam = poster_camera(model_dir, static)
        frame, image = 0, render_still(static, cam)
    else:
        gop = load_gop(model_dir, meta, 0)
        cam = poster_camera(model_dir, gop)
        frame = meta.shape.gop_size // 2
        image = FrameRenderer(gop, static=static).render(frame, cam)
    rgb = (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    return rgb, {"camera": cam.name, "frame": frame}


def encode_poster(rgb: np.ndarray) -> bytes:
    """The poster as WebP bytes."""
    ok, data = cv2.imencode(".webp", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_WEBP_QUALITY, POSTER_QUALITY])
    if not ok:
        raise StgsError("OpenCV could not encode the poster as WebP")
    return data.tobytes()


def scene_document(title: str, description: str, poster: str | None, view: dict | None) -> bytes:
    """scene.json (stgs.tree.SCENE): what a catalogue shows of the scene; `poster` relative to the MPD."""
    doc = {"format": SCENE_FORMAT, "version": 1, "title": title, "description": description, "poster": poster,
           "poster_view": view}
    return (json.dumps(doc, indent=1, ensure_ascii=False) + "\n").encode()
