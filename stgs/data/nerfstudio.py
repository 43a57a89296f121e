"""nerfstudio's `transforms.json`: one entry per image, `file_path` and `transform_matrix` (camera-to-world,
OpenGL axes: x right, y up, z backwards), intrinsics (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, `k1`..`k4`, `p1`,
`p2`, `camera_model`, or `camera_angle_x`) at the top for every image or in an entry for its own; a foreground
mask per image where an entry has `mask_path`.

A multi-view video needs to know which camera took which image and when: an entry's `camera` key (and `time`,
whose distinct values in order are the frames), or else each camera's images in a folder of its own
(`images/<cam>/<frame>.png`, frames in name order).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera
from stgs.data.distortion import Intrinsics
from stgs.data.frames import DEFAULT_CACHE, DEFAULT_FPS, natural_key, read_undistorted, read_undistorted_mask
from stgs.data.images import check_image_sizes, image_size
from stgs.errors import StgsError

TRANSFORMS = "transforms.json"
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
INTRINSIC_KEYS = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                  "camera_angle_x", "camera_angle_y")
MAX_TRANSFORMS_BYTES = 1 << 28
"""Largest transforms.json read."""


def opengl_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    """World-to-camera, OpenCV axes, of a camera-to-world matrix in OpenGL axes."""
    return np.linalg.inv(c2w @ OPENGL_TO_OPENCV)


def viewmat_to_opengl(viewmat: np.ndarray) -> np.ndarray:
    """The inverse of opengl_to_viewmat (what a transforms.json stores for an OpenCV world-to-camera)."""
    return np.linalg.inv(viewmat) @ OPENGL_TO_OPENCV


def _intrinsics(entry: dict, where: str, size: tuple[int, int] | None) -> Intrinsics:
    """An entry's intrinsics (the top level's merged under it)."""
    try:
        w, h = (int(entry["w"]), int(entry["h"])) if "w" in entry and "h" in entry else size or (0, 0)
        if not (w > 0 and h > 0):
            raise ValueError("no image size (w, h) and no readable image to take it from")
        if "fl_x" in entry:
            fx = float(entry["fl_x"])
            fy = float(entry.get("fl_y", fx))
        elif "camera_angle_x" in entry:
            fx = 0.5 * w / math.tan(0.5 * float(entry["camera_angle_x"]))
            fy = 0.5 * h / math.tan(0.5 * float(entry["camera_angle_y"])) if "camera_angle_y" in entry else fx
        else:
            raise ValueError("no focal length (fl_x or camera_angle_x)")
        cx, cy = float(entry.get("cx", w / 2)), float(entry.get("cy", h / 2))
        k = [float(entry.get(name, 0.0)) for name in ("k1", "k2", "k3", "k4", "p1", "p2")]
        model = str(entry.get("camera_model", "OPENCV"))
        if model in ("PINHOLE", "SIMPLE_PINHOLE") or (model == "OPENCV" and not any(k)):
            return Intrinsics.from_colmap("PINHOLE", w, h, [fx, fy, cx, cy])
        if model == "OPENCV":
            if k[3]:
                raise ValueError("k4 is set for the OPENCV model (only the fisheye model has it)")
            if k[2]:
                return Intrinsics.from_colmap("FULL_OPENCV", w, h, [fx, fy, cx, cy, k[0], k[1], k[4], k[5], k[2],
                                                                    0, 0, 0])
            return Intrinsics.from_colmap("OPENCV", w, h, [fx, fy, cx, cy, k[0], k[1], k[4], k[5]])
        if model == "OPENCV_FISHEYE":
            return Intrinsics.from_colmap("OPENCV_FISHEYE", w, h, [fx, fy, cx, cy, *k[:4]])
        raise ValueError(f"camera_model {model} is not supported (OPENCV, OPENCV_FISHEYE, PINHOLE)")
    except (TypeError, ValueError) as exc:
        raise StgsError(f"{where}: {exc}") from None


class NerfstudioReader:
    """A multi-view capture described by a nerfstudio transforms.json (the Dataset interface of stgs.data)."""

    def __init__(self, root: Path, holdout: list[str] | None = None, fps: float | None = None,
                 cache: Path | None = None):
        path = Path(root)
        self.root = path.parent if path.name == TRANSFORMS else path
        self.path = self.root / TRANSFORMS
        self.name = f"nerfstudio:{self.root.name}"
        self.cache = Path(cache or DEFAULT_CACHE)
        try:
            if self.path.stat().st_size > MAX_TRANSFORMS_BYTES:
                raise StgsError(f"{self.path}: larger than {MAX_TRANSFORMS_BYTES} bytes")
            doc = json.loads(self.path.read_text())
            entries = doc["frames"]
            if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
                raise TypeError("frames must be a non-empty list of objects")
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise StgsError(f"{self.path}: not a readable transforms.json ({exc})") from None
        top = {k: doc[k] for k in INTRINSIC_KEYS if k in doc}
        try:
            self.fps = float(fps or doc.get("fps", DEFAULT_FPS))
        except (TypeError, ValueError):
            raise StgsError(f"{self.path}: fps must be a number") from None
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise StgsError(f"{self.path}: fps must be positive, not {self.fps}")
        groups = self._group(entries)
        self.camera_names = sorted(groups, key=natural_key)
        counts = {name: len(items) for name, items in groups.items()}
        if len(set(counts.values())) > 1:
            odd = min(counts, key=lambda name: counts[name])
            most = max(counts, key=lambda name: counts[name])
            raise StgsError(f"{self.path}: camera {odd} has {counts[odd]} frames, {most} has {counts[most]} (every "
                            "camera needs the same frames)")
        self.num_frames = next(iter(counts.values()))
        self._files: dict[str, list[Path]] = {}
        self._masks: dict[str, list[Path | None]] = {}
        self._poses: dict[str, list[torch.Tensor]] = {}
        self._intrinsics: dict[str, Intrinsics] = {}
        for name in self.camera_names:
            items = groups[name]
            first = items[0]
            file = self.root / str(first["file_path"])
            where = f"{self.path}: frame {first['file_path']!r}"
            self._intrinsics[name] = _intrinsics(top | {k: first[k] for k in INTRINSIC_KEYS if k in first}, where,
                                                 image_size(file) if file.is_file() else None)
            self._files[name] = [self.root / str(e["file_path"]) for e in items]
            self._masks[name] = [self.root / str(e["mask_path"]) if "mask_path" in e else None for e in items]
            self._poses[name] = [self._viewmat(e) for e in items]
        self.default_holdout = list(holdout) if holdout is not None else []

    @classmethod
    def recognises(cls, path: Path) -> bool:
        path = Path(path)
        return (path / TRANSFORMS).is_file() or (path.name == TRANSFORMS and path.is_file())

    def _group(self, entries: list[dict]) -> dict[str, list[dict]]:
        """Camera name -> its entries in frame order."""
        for i, e in enumerate(entries):
            if "file_path" not in e or "transform_matrix" not in e:
                raise StgsError(f"{self.path}: frame {i} lacks file_path or transform_matrix")
        groups: dict[str, list[dict]] = defaultdict(list)
        if all("camera" in e for e in entries):
            for e in entries:
                groups[str(e["camera"])].append(e)
            if all("time" in e for e in entries):
                times = sorted({float(e["time"]) for e in entries})
                for name, items in groups.items():
                    own = sorted(float(e["time"]) for e in items)
                    if own != times:
                        raise StgsError(f"{self.path}: camera {name} lacks some of the times the others have "
                                        f"({len(own)} of {len(times)})")
                    items.sort(key=lambda e: float(e["time"]))
            else:
                for items in groups.values():
                    items.sort(key=lambda e: natural_key(str(e["file_path"])))
            return dict(groups)
        parents = {Path(str(e["file_path"])).parent.name for e in entries}
        if len(parents) > 1:
            for e in entries:
                groups[Path(str(e["file_path"])).parent.name].append(e)
            for items in groups.values():
                items.sort(key=lambda e: natural_key(Path(str(e["file_path"])).name))
            return dict(groups)
        raise StgsError(f"{self.path}: cannot tell which camera took each image: give every frame a \"camera\" key "
                        "(and a \"time\"), or put each camera's images in a folder of its own (images/<cam>/...)")

    def _viewmat(self, entry: dict) -> torch.Tensor:
        try:
            c2w = np.array(entry["transform_matrix"], dtype=np.float64)
            if c2w.shape == (3, 4):
                c2w = np.vstack([c2w, [0, 0, 0, 1]])
            if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
                raise ValueError
            rot = c2w[:3, :3]
            if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-4) or np.linalg.det(rot) < 0:
                raise ValueError
        except (TypeError, ValueError):
            raise StgsError(f"{self.path}: frame {entry['file_path']!r}: transform_matrix is not a finite rigid "
                            "4x4 (or 3x4) camera-to-world matrix") from None
        return torch.from_numpy(opengl_to_viewmat(c2w))

    def intrinsics(self, camera: str, frame: int = 0) -> Intrinsics:
        return self._intrinsics[camera]

    def _check(self, frame: int, camera: str) -> None:
        if camera not in self._intrinsics or not 0 <= frame < self.num_frames:
            raise StgsError(f"{self.name}: no frame {frame} of camera {camera!r}")

    def cameras(self, frame: int) -> list[Camera]:
        if not 0 <= frame < self.num_frames:
            raise StgsError(f"{self.name}: frame {frame} is outside 0..{self.num_frames - 1}")
        return [Camera(n, self._intrinsics[n].matrix(), self._poses[n][frame].clone(), self._intrinsics[n].width,
                       self._intrinsics[n].height) for n in self.camera_names]

    def pixels(self, frame: int, camera: str) -> np.ndarray:
        self._check(frame, camera)
        return read_undistorted(self._files[camera][frame], self._intrinsics[camera], self.cache)

    def image(self, frame: int, camera: str) -> torch.Tensor:
        return torch.from_numpy(self.pixels(frame, camera)).float().div_(255.0)

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        """The frame's `mask_path` (any non-zero pixel foreground), or None where it has none."""
        self._check(frame, camera)
        path = self._masks[camera][frame]
        return None if path is None else read_undistorted_mask(path, self._intrinsics[camera])

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None

    def check_views(self, frames: list[int], cameras: list[str]) -> None:
        check_image_sizes(self.root, [(self._files[c][f], (self._intrinsics[c].width, self._intrinsics[c].height))
                                      for f in frames for c in cameras])
