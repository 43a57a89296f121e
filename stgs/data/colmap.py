"""COLMAP sparse models (`cameras`, `images`, `points3D`, binary `.bin` or text `.txt`), read as COLMAP documents
them (https://colmap.github.io/format.html).

The reader is ours rather than pycolmap's: pycolmap's accepts a truncated cameras.bin and aborts the process on a
truncated points3D.bin, and a capture is user input, which gets one clear line. Every count in a binary file is
checked against the bytes left before anything is allocated. The tests hold this reader to pycolmap's on the same
files. Rigs and frames (COLMAP 3.12's `rigs`, `frames`) are not read: `images` still carries every image's pose.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stgs.data.distortion import MODELS, Intrinsics
from stgs.errors import StgsError

MODEL_IDS = {0: "SIMPLE_PINHOLE", 1: "PINHOLE", 2: "SIMPLE_RADIAL", 3: "RADIAL", 4: "OPENCV", 5: "OPENCV_FISHEYE",
             6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE", 10: "THIN_PRISM_FISHEYE",
             11: "RAD_TAN_THIN_PRISM_FISHEYE"}
"""COLMAP's camera model ids (src/colmap/sensor/models.h)."""
PARAM_COUNTS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "OPENCV_FISHEYE": 8,
                "FULL_OPENCV": 12, "FOV": 5, "SIMPLE_RADIAL_FISHEYE": 4, "RADIAL_FISHEYE": 5,
                "THIN_PRISM_FISHEYE": 12, "RAD_TAN_THIN_PRISM_FISHEYE": 16}
MAX_NAME_BYTES = 4096
"""Longest image name read (a binary name runs to its NUL byte)."""


class ColmapError(StgsError):
    """A COLMAP model that cannot be read (one line naming the file and what is wrong)."""


@dataclass
class ColmapImage:
    """One registered image: its camera and its pose."""

    image_id: int
    name: str
    camera_id: int
    qvec: np.ndarray
    """(4,) wxyz rotation world to camera (float64, as stored)."""
    tvec: np.ndarray
    """(3,) translation world to camera (float64)."""

    def viewmat(self) -> np.ndarray:
        """(4, 4) world-to-camera, OpenCV axes (COLMAP's own)."""
        w, x, y, z = self.qvec / np.linalg.norm(self.qvec)
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = rot, self.tvec
        return view


@dataclass
class ColmapModel:
    """A sparse model: cameras by id, registered images, and the 3D points (xyz float64, rgb uint8)."""

    path: Path
    cameras: dict[int, Intrinsics]
    images: list[ColmapImage]
    points: np.ndarray
    """(P, 3) float64 positions."""
    colours: np.ndarray
    """(P, 3) uint8 RGB."""


class _Bytes:
    """A cursor over a binary file whose every read is checked against the bytes left."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def left(self) -> int:
        return len(self.data) - self.at

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if size > self.left():
            raise ColmapError(f"{self.path}: truncated at byte {self.at} (expected {size} more)")
        values = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return values

    def count(self, min_entry_bytes: int, what: str) -> int:
        """A uint64 count of entries of at least `min_entry_bytes` each, checked against the file's length."""
        (n,) = self.read("<Q")
        if n * min_entry_bytes > self.left():
            raise ColmapError(f"{self.path}: says {n} {what}, more than its {self.left()} bytes left can hold "
                              "(truncated or not a COLMAP model)")
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.at, self.at + MAX_NAME_BYTES)
        if end < 0:
            raise ColmapError(f"{self.path}: image name at byte {self.at} has no end (truncated?)")
        raw, self.at = self.data[self.at:end], end + 1
        try:
            return raw.decode()
        except UnicodeDecodeError:
            raise ColmapError(f"{self.path}: image name at byte {self.at} is not UTF-8") from None

    def array(self, dtype: str, count: int) -> np.ndarray:
        size = np.dtype(dtype).itemsize * count
        if size > self.left():
            raise ColmapError(f"{self.path}: truncated at byte {self.at} (expected {size} more)")
        out = np.frombuffer(self.data, dtype, count, self.at)
        self.at += size
        return out

    def done(self) -> None:
        if self.left():
            raise ColmapError(f"{self.path}: {self.left()} bytes after the last entry (not a COLMAP model?)")


def model_name(model_id: int) -> str:
    """A camera model id's COLMAP name (ids newer than this reader's table named by pycolmap where it knows them)."""
    if model_id in MODEL_IDS:
        return MODEL_IDS[model_id]
    try:
        import pycolmap

        return pycolmap.CameraModelId(model_id).name
    except (ImportError, ValueError, TypeError):
        return f"id {model_id}"


def _camera(path: Path, camera_id: int, model: str, width: int, height: int, params: list[float]) -> Intrinsics:
    if model not in MODELS:
        raise ColmapError(f"{path}: camera {camera_id} uses the {model} model, which this reader does not undistort "
                          f"(supported: {', '.join(MODELS)})")
    if len(params) != PARAM_COUNTS[model]:
        raise ColmapError(f"{path}: camera {camera_id} ({model}) has {len(params)} parameters, not "
                          f"{PARAM_COUNTS[model]}")
    if not (0 < width <= 1 << 16 and 0 < height <= 1 << 16):
        raise ColmapError(f"{path}: camera {camera_id} is {width}x{height} pixels")
    try:
        return Intrinsics.from_colmap(model, width, height, params)
    except ValueError as exc:
        raise ColmapError(f"{path}: camera {camera_id}: {exc}") from None


def _cameras_bin(path: Path) -> dict[int, Intrinsics]:
    f = _Bytes(path)
    cameras = {}
    for _ in range(f.count(24, "cameras")):
        camera_id, model_id, width, height = f.read("<iiQQ")
        if model_id not in MODEL_IDS:  # an unknown model's parameter count is unknown: nothing after it reads
            raise ColmapError(f"{path}: camera {camera_id} uses the {model_name(model_id)} model, which this reader "
                              f"does not undistort (supported: {', '.join(MODELS)})")
        model = MODEL_IDS[model_id]
        params = f.read(f"<{PARAM_COUNTS[model]}d")
        cameras[camera_id] = _camera(path, camera_id, model, width, height, list(params))
    f.done()
    return cameras


def _images_bin(path: Path) -> list[ColmapImage]:
    f = _Bytes(path)
    images = []
    for _ in range(f.count(4 + 56 + 4 + 1 + 8, "images")):
        (image_id,), pose, (camera_id,) = f.read("<I"), f.read("<7d"), f.read("<I")
        name = f.name()
        points = f.count(24, "2D points")
        f.at += 24 * points  # nothing kept of the 2D points (x, y, point3D id); count() checked their bytes
        images.append(ColmapImage(image_id, name, camera_id, np.array(pose[:4]), np.array(pose[4:])))
    f.done()
    return images


def _points_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    f = _Bytes(path)
    n = f.count(8 + 24 + 3 + 8 + 8, "points")
    xyz, rgb = np.empty((n, 3)), np.empty((n, 3), np.uint8)
    for i in range(n):
        _, x, y, z, r, g, b, _, track = f.read("<Q3d3BdQ")
        if 8 * track > f.left():
            raise ColmapError(f"{path}: point {i} has a track of {track} longer than the file")
        f.at += 8 * track
        xyz[i], rgb[i] = (x, y, z), (r, g, b)
    f.done()
    return xyz, rgb


def _lines(path: Path) -> list[str]:
    """The file's lines, comments dropped; blank lines kept (images.txt's empty 2D-point lines)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ColmapError(f"{path}: unreadable ({exc})") from None
    return [line.strip() for line in text.splitlines() if not line.lstrip().startswith("#")]


def _cameras_txt(path: Path) -> dict[int, Intrinsics]:
    cameras = {}
    for n, line in enumerate(filter(None, _lines(path)), 1):
        parts = line.split()
        try:
            camera_id, model, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = [float(p) for p in parts[4:]]
        except (IndexError, ValueError):
            raise ColmapError(f"{path}: camera line {n} is not CAMERA_ID MODEL WIDTH HEIGHT PARAMS...") from None
        cameras[camera_id] = _camera(path, camera_id, model, width, height, params)
    return cameras


def _images_txt(path: Path) -> list[ColmapImage]:
    lines = _lines(path)
    while lines and not lines[-1]:
        lines.pop()
    images = []
    for n in range(0, len(lines), 2):
        parts = lines[n].split(maxsplit=9)
        try:
            values = [float(p) for p in parts[1:8]]
            image = ColmapImage(int(parts[0]), parts[9], int(parts[8]), np.array(values[:4]), np.array(values[4:]))
        except (IndexError, ValueError):
            raise ColmapError(f"{path}: image entry {n // 2 + 1} is not IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID "
                              "NAME") from None
        images.append(image)
    return images


def _points_txt(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = [], []
    for n, line in enumerate(filter(None, _lines(path)), 1):
        parts = line.split()
        try:
            xyz.append([float(v) for v in parts[1:4]])
            rgb.append([int(v) for v in parts[4:7]])
            if len(xyz[-1]) != 3 or len(rgb[-1]) != 3 or not all(0 <= v <= 255 for v in rgb[-1]):
                raise ValueError
        except ValueError:
            raise ColmapError(f"{path}: point line {n} is not POINT3D_ID X Y Z R G B ERROR TRACK...") from None
    return np.array(xyz, dtype=np.float64).reshape(-1, 3), np.array(rgb, dtype=np.uint8).reshape(-1, 3)


def find_model(folder: Path) -> str | None:
    """The extension ("bin" or "txt") of the COLMAP model in `folder`, or None where it holds none."""
    for ext in ("bin", "txt"):
        if (folder / f"cameras.{ext}").is_file() and (folder / f"images.{ext}").is_file():
            return ext
    return None


def read_model(folder: Path) -> ColmapModel:
    """The sparse model in `folder` (binary preferred where both are there); points3D is optional."""
    folder = Path(folder)
    ext = find_model(folder)
    if ext is None:
        raise ColmapError(f"{folder}: no COLMAP model (cameras.bin + images.bin, or cameras.txt + images.txt)")
    binary = ext == "bin"
    try:
        cameras = (_cameras_bin if binary else _cameras_txt)(folder / f"cameras.{ext}")
        images = (_images_bin if binary else _images_txt)(folder / f"images.{ext}")
        points = folder / f"points3D.{ext}"
        xyz, rgb = (_points_bin if binary else _points_txt)(points) if points.is_file() else \
            (np.empty((0, 3)), np.empty((0, 3), np.uint8))
    except OSError as exc:
        raise ColmapError(f"{folder}: unreadable ({exc})") from None
    for image in images:
        if image.camera_id not in cameras:
            raise ColmapError(f"{folder}: image {image.name!r} refers to camera {image.camera_id}, which "
                              f"cameras.{ext} lacks")
        if not (np.isfinite(image.qvec).all() and np.isfinite(image.tvec).all() and np.linalg.norm(image.qvec) > 0):
            raise ColmapError(f"{folder}: image {image.name!r} has no valid pose")
    if not images:
        raise ColmapError(f"{folder}: the model registers no image")
    return ColmapModel(folder, cameras, images, xyz, rgb)
