"""Where a capture's frames come from, shared by the readers: image files (undistorted once into a cache where the
lens distorts), their foreground masks where the capture has them, and videos (decoded once per camera, a frame
at a time, into lossless PNGs in a cache).

The caches live under STGS_DATA_CACHE (default ~/.cache/stgs/frames), keyed by the source's path, size and
modification time and the calibration: a changed file or calibration is read afresh. Every file is written to
a temporary name and renamed into place, so a cache never holds half a frame.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import av
import cv2
import numpy as np
import torch

from stgs.data.distortion import Intrinsics
from stgs.data.images import read_mask, read_rgb8
from stgs.errors import StgsError

DEFAULT_CACHE = Path(os.environ.get("STGS_DATA_CACHE", Path.home() / ".cache" / "stgs" / "frames"))
DEFAULT_FPS = 30.0
"""The frame rate of a capture of image files, which do not say theirs (the readers' `fps` sets it)."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".webp")
"""Files a frame folder's images may be (by suffix, any case)."""


def natural_key(name: str) -> tuple:
    """Sort key that orders the digits in a name by their value: cam2 before cam10, frame_9 before frame_10."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name))


def image_files(folder: Path) -> list[Path]:
    """The image files directly in `folder`, in natural_key order of their names."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=lambda p: natural_key(p.name))


def source_key(*parts: object) -> str:
    """A cache key of files (path, size, modification time) and calibrations (their JSON)."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, Path):
            stat = part.stat()
            part = f"{part.resolve()}:{stat.st_size}:{stat.st_mtime_ns}"
        elif isinstance(part, Intrinsics):
            part = json.dumps(part.to_json(), sort_keys=True)
        h.update(str(part).encode() + b"\0")
    return h.hexdigest()[:20]


def write_png(path: Path, rgb: np.ndarray) -> None:
    """`rgb` (H, W, 3) uint8 as a lossless PNG at `path`, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        if not cv2.imwrite(tmp, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise StgsError(f"{path.parent}: cannot write a cached frame")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_undistorted(path: Path, intrinsics: Intrinsics, cache: Path | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of the image file `path` taken through `intrinsics`' lens, undistorted (read from the
    cache after the first time); the file as it is where the camera is a pinhole one."""
    size = (intrinsics.height, intrinsics.width)
    if not intrinsics.distorted:
        return read_rgb8(path, size)
    cached = Path(cache or DEFAULT_CACHE) / "undistorted" / f"{source_key(path, intrinsics)}.png"
    if cached.is_file():
        try:
            return read_rgb8(cached, size)
        except StgsError:
            cached.unlink(missing_ok=True)  # a damaged cache entry is made again
    rgb = intrinsics.undistort(read_rgb8(path, size))
    write_png(cached, rgb)
    return rgb


def mask_file(folder: Path, stem: str) -> Path | None:
    """The mask `stem`.<image suffix> in `folder`, or None."""
    for suffix in IMAGE_SUFFIXES:
        path = folder / f"{stem}{suffix}"
        if path.is_file():
            return path
    return None


def read_undistorted_mask(path: Path, intrinsics: Intrinsics) -> torch.Tensor:
    """(H, W) bool foreground mask (any non-zero pixel) of the mask file `path`, undistorted as the camera's views
    are (nearest neighbour)."""
    mask = read_mask(path, (intrinsics.height, intrinsics.width)).numpy().astype(np.uint8)
    return torch.from_numpy(intrinsics.undistort(mask, nearest=True) > 0)


def count_video_frames(video: Path) -> int:
    """Frames of the video's first stream, counted from its packets (nothing is decoded)."""
    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise StgsError(f"{video}: holds no video stream")
            stream = container.streams.video[0]
            return sum(1 for packet in container.demux(stream) if packet.size)
    except av.FFmpegError as exc:
        raise StgsError(f"{video}: not a readable video ({exc.strerror or exc})") from None


def video_rate(video: Path) -> float | None:
    """The first video stream's average frame rate, or None where the container does not say."""
    try:
        with av.open(str(video)) as container:
            rate = container.streams.video[0].average_rate if container.streams.video else None
    except av.FFmpegError:
        return None
    return float(rate) if rate else None


def extract_video(video: Path, out: Path, size: tuple[int, int],
                  fix: Callable[[np.ndarray], np.ndarray] | None = None) -> Path:
    """Folder `out` holding the video's frames as `00000.png`..., each scaled to `size` (width, height) and passed
    through `fix` (RGB uint8 in and out; an undistortion), decoded once a frame at a time: the folder is filled
    under a temporary name and renamed into place, so it exists only whole."""
    if out.is_dir():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        with av.open(str(video)) as container:
            for i, frame in enumerate(container.decode(video=0)):
                bgr = frame.to_ndarray(width=size[0], height=size[1], format="bgr24", interpolation="AREA")
                if fix is not None:
                    bgr = np.ascontiguousarray(fix(np.ascontiguousarray(bgr[..., ::-1]))[..., ::-1])
                if not cv2.imwrite(str(tmp / f"{i:05d}.png"), bgr):
                    raise StgsError(f"{tmp}: cannot write frame {i}")
    except (av.FFmpegError, StgsError) as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        why = exc.strerror if isinstance(exc, av.FFmpegError) else exc
        raise StgsError(f"{video}: could not extract frames ({why})") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        tmp.rename(out)
    except OSError:  # another process extracted it first
        shutil.rmtree(tmp, ignore_errors=True)
    return out
