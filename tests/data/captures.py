"""A small synthetic capture written out in every layout the readers take, COLMAP models written by pycolmap (the
reference writer), videos losslessly with PyAV's FFV1."""

from __future__ import annotations

import json
from pathlib import Path

import av
import cv2
import numpy as np
import pycolmap

from stgs.camera import Camera
from stgs.data.distortion import Intrinsics
from stgs.data.nerfstudio import viewmat_to_opengl
from stgs.data.synth import SynthReader
from stgs.synth import SynthConfig
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.synth.generate import ProceduralScene, ground_truth_cameras, imported_backdrop, write_ground_truth

SCENE = SynthConfig(grid_side=8, num_gops=1, gop_size=4, width=64, height=48, num_cameras=5,
                    effects=("rigid", "color"))
TEXTURED = SynthConfig(grid_side=8, num_gops=1, gop_size=2, width=160, height=120, num_cameras=3,
                       effects=("rigid", "static_background"), static_grid_side=24)
"""A backdrop that fills the views: what a lens's distortion visibly moves."""
MOVING = SynthConfig(grid_side=16, num_gops=1, gop_size=6, width=96, height=72, num_cameras=8,
                     effects=DEFAULT_EFFECTS)
"""Enough views and motion for a quick training."""


def ground_truth(out: Path, cfg: SynthConfig = SCENE) -> SynthReader:
    """The synthetic scene's ground-truth views (no model fitted), read as a dataset."""
    layered = "static_background" in cfg.effects
    scene = ProceduralScene(cfg.grid_side ** 2, tuple(cfg.effects), cfg.seed,
                            cfg.static_grid_side ** 2 if layered else 0)
    if cfg.static_from is not None:
        scene.static = imported_backdrop(cfg)
    write_ground_truth(out, scene, cfg, ground_truth_cameras(cfg), progress=False)
    return SynthReader(out)


def colmap_params(cam: Camera, model: str = "PINHOLE", coefficients: tuple[float, ...] = ()) -> list[float]:
    """COLMAP's parameter list of `model` for the camera's (square-pixel, for the one-focal models) intrinsics."""
    K = cam.K.double().numpy()
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        return [K[0, 0], K[0, 2], K[1, 2], *coefficients]
    return [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *coefficients]


def write_colmap(folder: Path, cams: list[Camera], names: list[str], binary: bool = True, model: str = "PINHOLE",
                 coefficients: tuple[float, ...] = (), points: np.ndarray | None = None,
                 shift: np.ndarray | None = None, scale: float = 1.0) -> None:
    """A COLMAP model of `cams` (image names `names`, one camera each), written by pycolmap; `shift` moves every
    camera (a per-frame calibration), `scale` changes the unit of length (the world scaled about its origin)."""
    rec = pycolmap.Reconstruction()
    for i, (cam, name) in enumerate(zip(cams, names, strict=True), 1):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=i, model=model, width=cam.width, height=cam.height,
                                                        params=colmap_params(cam, model, coefficients)))
        view = cam.viewmat.double().numpy()
        t = (view[:3, 3] if shift is None else view[:3, 3] - view[:3, :3] @ shift) * scale
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(view[:3, :3]), t)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=i, image_id=i), pose)
    rng = np.random.default_rng(0)
    for p in (points if points is not None else []):
        rec.add_point3D(p * scale, pycolmap.Track(), rng.integers(0, 256, 3).astype(np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if binary else rec.write_text)(str(folder))


def _rgb(ds: SynthReader, frame: int, camera: str, lens: Intrinsics | None) -> np.ndarray:
    rgb = ds.pixels(frame, camera)
    return lens.distort(rgb) if lens is not None else rgb


def _png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


class FirstFrames:
    """The first `count` frames of a synthetic scene's views (a still capture: count 1)."""

    def __init__(self, ds: SynthReader, count: int):
        self.ds, self.num_frames, self.fps = ds, min(count, ds.num_frames), ds.fps

    def cameras(self, frame: int) -> list[Camera]:
        return self.ds.cameras(frame)

    def pixels(self, frame: int, camera: str):
        return self.ds.pixels(frame, camera)


def lens_of(cam: Camera, model: str, coefficients: tuple[float, ...]) -> Intrinsics | None:
    if model in ("PINHOLE", "SIMPLE_PINHOLE"):
        return None
    return Intrinsics.from_colmap(model, cam.width, cam.height, colmap_params(cam, model, coefficients))


def write_capture(ds: SynthReader, out: Path, layout: str, binary: bool = True, model: str = "PINHOLE",
                  coefficients: tuple[float, ...] = (), points: np.ndarray | None = None,
                  per_frame: bool = False, scale: float = 1.0, num_frames: int | None = None) -> Path:
    """`ds` as a capture in `layout` (frames, images, videos, nerfstudio) at `out`, its unit of length 1/`scale`
    of the synthetic scene's (COLMAP layouts); `num_frames`: its first frames only (None: all)."""
    if num_frames is not None:
        ds = FirstFrames(ds, num_frames)
    cams = ds.cameras(0)
    names = [c.name for c in cams]
    lenses = {c.name: lens_of(c, model, coefficients) for c in cams}
    if layout == "frames":
        for f in range(ds.num_frames):
            for c in names:
                _png(out / f"frame{f:06d}" / "images" / f"{c}.png", _rgb(ds, f, c, lenses[c]))
            if per_frame or f == 0:
                shift = np.array([0.01 * f, 0.0, 0.0]) if per_frame else None
                write_colmap(out / f"frame{f:06d}" / "sparse" / "0", cams, [f"{c}.png" for c in names], binary,
                             model, coefficients, points, shift, scale)
    elif layout == "images":
        for f in range(ds.num_frames):
            for c in names:
                _png(out / "images" / c / f"{f:06d}.png", _rgb(ds, f, c, lenses[c]))
        write_colmap(out / "sparse" / "0", cams, [f"{c}/000000.png" for c in names], binary, model, coefficients,
                     points)
    elif layout == "videos":
        for c in names:
            path = out / "videos" / f"{c}.mkv"
            path.parent.mkdir(parents=True, exist_ok=True)
            with av.open(str(path), "w") as container:
                stream = container.add_stream("ffv1", rate=30)
                stream.width, stream.height, stream.pix_fmt = cams[0].width, cams[0].height, "bgr0"
                for f in range(ds.num_frames):
                    frame = av.VideoFrame.from_ndarray(_rgb(ds, f, c, lenses[c]), format="rgb24")
                    container.mux(stream.encode(frame))
                container.mux(stream.encode())
        write_colmap(out / "sparse" / "0", cams, [f"{c}.png" for c in names], binary, model, coefficients, points)
    elif layout == "nerfstudio":
        frames = []
        for f in range(ds.num_frames):
            for cam in cams:
                rel = f"images/{cam.name}/{f:05d}.png"
                _png(out / rel, _rgb(ds, f, cam.name, lenses[cam.name]))
                frames.append({"file_path": rel, "camera": cam.name, "time": f / ds.fps,
                               "transform_matrix": viewmat_to_opengl(cam.viewmat.double().numpy()).tolist()})
        K = cams[0].K.double().numpy()
        doc = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
               "w": cams[0].width, "h": cams[0].height, "frames": frames}
        (out / "transforms.json").write_text(json.dumps(doc))
    else:
        raise ValueError(layout)
    return out
