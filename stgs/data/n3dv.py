"""Neural 3D Video (N3DV / DyNeRF) layout: LLFF `poses_bounds.npy` + one `camNN.mp4` per camera.

poses_bounds.npy is (cameras, 17): a 3x5 matrix per camera, columns
[down, right, back | centre | (height, width, focal)] in LLFF's axes, then
near/far bounds. Cameras are sorted by name, matched to the rows in order.
Frames are decoded once per camera (PyAV, the project's one video route),
downscaled by `downscale` (2 by custom) with area averaging, and kept as
lossless PNGs in a cache folder; cam00 is held out.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera
from stgs.data.frames import DEFAULT_CACHE, count_video_frames, extract_video
from stgs.data.images import read_rgb8
from stgs.errors import StgsError

POSES = "poses_bounds.npy"


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
        self.num_frames = min(count_video_frames(v) for v in videos)

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (Path(path) / POSES).is_file()

    def cameras(self, frame: int) -> list[Camera]:
        return list(self._cams)

    def _extract(self, camera: str) -> Path:
        """The camera's frames as PNGs (extracted on first use: stgs.data.frames.extract_video)."""
        cam = self._cams[self.camera_names.index(camera)]
        return extract_video(self._videos[camera], self.frames_dir / camera, (cam.width, cam.height))

    def image(self, frame: int, camera: str) -> torch.Tensor:
        return torch.from_numpy(self.pixels(frame, camera)).float().div_(255.0)

    def pixels(self, frame: int, camera: str) -> np.ndarray:
        if camera not in self._videos or not 0 <= frame < self.num_frames:
            raise StgsError(f"{self.name}: no frame {frame} of camera {camera!r}")
        cam = self._cams[self.camera_names.index(camera)]
        return read_rgb8(self._extract(camera) / f"{frame:05d}.png", (cam.height, cam.width))

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        return None

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None

    def check_views(self, frames: list[int], cameras: list[str]) -> None:
        """Nothing beyond the constructor's checks: every camera's frames are counted from its video, and each
        frame is scaled to its camera's size as it is extracted."""
