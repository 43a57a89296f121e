"""Neural 3D Video (N3DV / DyNeRF) layout: LLFF `poses_bounds.npy` + one `camNN.mp4` per camera.

poses_bounds.npy is (cameras, 17): a 3x5 matrix per camera, columns
[down, right, back | centre | (height, width, focal)] in LLFF's axes, then
near/far bounds. Cameras are sorted by name, matched to the rows in order.
Frames are extracted once per camera with ffmpeg, downscaled by `downscale`
(2 by custom), as lossless PNGs into a cache folder; cam00 is held out.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera
from stgs.codec import ffmpeg
from stgs.codec.ffmpeg import require_ffmpeg
from stgs.data.images import read_rgb
from stgs.errors import StgsError

POSES = "poses_bounds.npy"
DEFAULT_CACHE = Path(os.environ.get("STGS_DATA_CACHE", Path.home() / ".cache" / "stgs" / "frames"))


def llff_to_opencv(row: np.ndarray, downscale: float) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """(K, world-to-camera, width, height) of one poses_bounds row."""
    mat = row[:15].reshape(3, 5).astype(np.float64)
    down, right, back, centre = mat[:, 0], mat[:, 1], mat[:, 2], mat[:, 3]
    h, w, focal = mat[:, 4]
    rot = np.stack([right, down, -back])  # rows: camera x, y, z axes in world coordinates
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ centre
    width, height, f = round(w / downscale), round(h / downscale), focal / downscale
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return torch.from_numpy(K), torch.from_numpy(view), width, height


class N3DVReader:
    def __init__(self, root: Path, holdout: list[str] | None = None, downscale: int = 2,
                 cache: Path | None = None, fps: float = 30.0):
        self.root = Path(root)
        self.name = f"n3dv:{self.root.name}"
        self.fps = fps
        videos = sorted(self.root.glob("cam*.mp4"))
        try:
            poses = np.load(self.root / POSES, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise StgsError(f"{self.root}: cannot read {POSES} ({exc})") from None
        if poses.ndim != 2 or poses.shape[1] != 17 or not np.isfinite(poses).all():
            raise StgsError(f"{self.root / POSES}: expected a finite (cameras, 17) array, got {poses.shape}")
        if len(videos) != len(poses):
            raise StgsError(f"{self.root}: {len(videos)} cam*.mp4 video(s) but {len(poses)} camera pose(s) in {POSES}")
        if not videos:
            raise StgsError(f"{self.root}: no cam*.mp4 videos")
        require_ffmpeg()
        self.camera_names = [v.stem for v in videos]
        self.default_holdout = list(holdout) if holdout is not None else ["cam00"][: len(videos) - 1]
        self._videos = dict(zip(self.camera_names, videos, strict=True))
        self._cams = []
        for name, row in zip(self.camera_names, poses, strict=True):
            K, view, w, h = llff_to_opencv(row, downscale)
            self._cams.append(Camera(name, K, view, w, h))
        key = hashlib.sha256(f"{self.root.resolve()}:{downscale}".encode()).hexdigest()[:16]
        self.frames_dir = Path(cache or DEFAULT_CACHE) / f"n3dv-{key}"
        self.downscale = downscale
        self.num_frames = min(self._frame_count(v) for v in videos)

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (Path(path) / POSES).is_file()

    @staticmethod
    def _frame_count(video: Path) -> int:
        args = ["-select_streams", "v:0", "-count_packets", "-show_entries", "stream=nb_read_packets",
                "-of", "csv=p=0", str(video)]
        try:
            return int(ffmpeg.run(args, tool="ffprobe").decode().strip().split(",")[0])
        except (ffmpeg.FFmpegError, ValueError) as exc:
            raise StgsError(f"{video}: not a readable video ({str(exc)[:200]})") from None

    def cameras(self, frame: int) -> list[Camera]:
        return list(self._cams)

    def _extract(self, camera: str) -> Path:
        """The camera's frames as PNGs (extracted on first use; atomic: a temp folder renamed into place)."""
        out = self.frames_dir / camera
        if out.is_dir():
            return out
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{camera}.", dir=self.frames_dir))
        cam = self._cams[self.camera_names.index(camera)]
        args = ["-i", str(self._videos[camera]), "-vf", f"scale={cam.width}:{cam.height}:flags=area",
                "-start_number", "0", str(tmp / "%05d.png")]
        try:
            ffmpeg.run(args)
        except ffmpeg.FFmpegError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise StgsError(f"{self._videos[camera]}: ffmpeg could not extract frames ({str(exc)[:200]})") from None
        try:
            tmp.rename(out)
        except OSError:  # another process extracted it first
            shutil.rmtree(tmp, ignore_errors=True)
        return out

    def image(self, frame: int, camera: str) -> torch.Tensor:
        if camera not in self._videos or not 0 <= frame < self.num_frames:
            raise StgsError(f"{self.name}: no frame {frame} of camera {camera!r}")
        cam = self._cams[self.camera_names.index(camera)]
        return read_rgb(self._extract(camera) / f"{frame:05d}.png", (cam.height, cam.width))

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        return None
