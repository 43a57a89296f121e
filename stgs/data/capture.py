"""Calibrated captures: a COLMAP model (stgs.data.colmap) and the frames of every camera in one of three layouts
(docs/CAPTURE.md):

- `frames`: one folder per frame, `frameNNNNNN/images/<cam>.<ext>` (3DGStream and the streaming methods after
  it), the model in `frame000000/sparse/0` or `sparse/0` at the top; where every frame folder has its own
  `sparse/0`, each frame's cameras are its own; foreground masks, where there are any, in
  `frameNNNNNN/masks/<cam>.<ext>`;
- `images`: one folder per camera, `images/<cam>/<frame>.<ext>`, frames in name order, the model in `sparse/0`;
  masks in `masks/<cam>/<frame>.<ext>`;
- `videos`: one video per camera, `videos/<cam>.<ext>` (any container PyAV reads), the model in `sparse/0`,
  decoded once per camera into a cache of lossless PNGs.

The model's images are matched to the cameras by name: the file's stem (`cam00.png`), or in the per-camera
layouts the folder that holds it (`cam00/000000.png`). Cameras and frames are in natural order (cam2 before cam10).
Distorted cameras are undistorted once into a cache
(stgs.data.distortion). The model's points3D seed training where the model has them (`points`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera
from stgs.data.colmap import ColmapModel, find_model, read_model
from stgs.data.distortion import Intrinsics
from stgs.data.frames import (
    DEFAULT_CACHE,
    DEFAULT_FPS,
    count_video_frames,
    extract_video,
    image_files,
    mask_file,
    natural_key,
    read_undistorted,
    read_undistorted_mask,
    source_key,
    video_rate,
)
from stgs.data.images import check_image_sizes, read_rgb8
from stgs.errors import StgsError

LAYOUTS = ("frames", "images", "videos")
FRAME_DIR = re.compile(r"frame(\d+)$")


def frame_dirs(root: Path) -> list[Path]:
    """The per-frame layout's frame folders (`frameNNNNNN` holding `images/`), in frame order."""
    found = [(int(m.group(1)), p) for p in root.iterdir() if (m := FRAME_DIR.match(p.name)) and (p / "images").is_dir()]
    return [p for _, p in sorted(found)]


def top_model(root: Path) -> Path | None:
    """`sparse/0` or `sparse` at the top of a capture, where it holds a COLMAP model."""
    for folder in (root / "sparse" / "0", root / "sparse"):
        if folder.is_dir() and find_model(folder):
            return folder
    return None


def detect_layout(root: Path) -> str | None:
    """The layout of the capture at `root`, or None."""
    root = Path(root)
    if not root.is_dir():
        return None
    if frame_dirs(root):
        return "frames"
    if (root / "images").is_dir() and any(p.is_dir() for p in (root / "images").iterdir()) and top_model(root):
        return "images"
    if (root / "videos").is_dir() and top_model(root):
        return "videos"
    return None


def camera_key(image_name: str, layout: str) -> str:
    """The camera a model's image name stands for in `layout`."""
    path = Path(image_name)
    if layout == "frames":
        return path.stem
    return path.parent.name or path.stem


class ColmapReader:
    """A COLMAP-calibrated capture in one of LAYOUTS (the Dataset interface of stgs.data)."""

    def __init__(self, root: Path, layout: str | None = None, holdout: list[str] | None = None,
                 fps: float | None = None, cache: Path | None = None):
        self.root = Path(root)
        found = layout or detect_layout(self.root)
        if found not in LAYOUTS:
            raise StgsError(f"{self.root}: not a COLMAP capture (frameNNNNNN/images/ folders, or images/<cam>/ or "
                            "videos/ beside sparse/0)")
        self.layout: str = found
        self.name = f"colmap-{self.layout}:{self.root.name}"
        self.cache = Path(cache or DEFAULT_CACHE)
        self._files: dict[str, list[Path]] = {}
        self._videos: dict[str, Path] = {}
        {"frames": self._scan_frames, "images": self._scan_images, "videos": self._scan_videos}[self.layout]()
        self.camera_names = sorted(self._files or self._videos, key=natural_key)
        if fps is not None and not fps > 0:
            raise StgsError(f"{self.name}: fps must be positive, not {fps}")
        rates = {r for v in self._videos.values() if (r := video_rate(v))}
        self.fps = float(fps or (min(rates) if rates else DEFAULT_FPS))
        self.models = self._models()
        """The calibration: one model for every frame, or one per frame (the per-frame layout's own models)."""
        self._calibration = [self._match(m) for m in self.models]
        cam00 = ["cam00"] if "cam00" in self.camera_names and len(self.camera_names) > 1 else []
        self.default_holdout = list(holdout) if holdout is not None else (cam00 if self.layout == "frames" else [])

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return detect_layout(Path(path)) is not None

    # --- what the layout holds ---

    def _scan_frames(self) -> None:
        dirs = frame_dirs(self.root) if self.root.is_dir() else []
        if not dirs:
            raise StgsError(f"{self.root}: no frame folders (frameNNNNNN/images/)")
        per_frame = [{p.stem: p for p in image_files(d / "images")} for d in dirs]
        names = set(per_frame[0])
        if not names:
            raise StgsError(f"{dirs[0] / 'images'}: holds no images")
        for d, files in zip(dirs, per_frame, strict=True):
            if set(files) != names:
                odd = sorted(names ^ set(files))[0]
                where = f"lacks {odd}" if odd in names else f"has {odd}, which {dirs[0].name} lacks"
                raise StgsError(f"{d / 'images'}: {where} (every frame holds the same cameras)")
        self._files = {name: [files[name] for files in per_frame] for name in sorted(names, key=natural_key)}
        self.num_frames = len(dirs)

    def _scan_images(self) -> None:
        if not (self.root / "images").is_dir():
            raise StgsError(f"{self.root}: no images/ folder (images/<cam>/<frame>.<ext>)")
        folders = sorted((p for p in (self.root / "images").iterdir() if p.is_dir()), key=lambda p: natural_key(p.name))
        self._files = {f.name: image_files(f) for f in folders}
        self.num_frames = self._same_counts({k: len(v) for k, v in self._files.items()}, "images")

    def _scan_videos(self) -> None:
        if not (self.root / "videos").is_dir():
            raise StgsError(f"{self.root}: no videos/ folder (videos/<cam>.<ext>)")
        videos = sorted((p for p in (self.root / "videos").iterdir() if p.is_file() and not p.name.startswith(".")),
                        key=lambda p: natural_key(p.name))
        if not videos:
            raise StgsError(f"{self.root / 'videos'}: holds no videos")
        stems = [v.stem for v in videos]
        if len(set(stems)) != len(stems):
            dup = next(s for s in stems if stems.count(s) > 1)
            raise StgsError(f"{self.root / 'videos'}: two files for camera {dup}")
        self._videos = dict(zip(stems, videos, strict=True))
        self.num_frames = self._same_counts({k: count_video_frames(v) for k, v in self._videos.items()}, "videos")

    def _same_counts(self, counts: dict[str, int], what: str) -> int:
        if not counts:
            raise StgsError(f"{self.root / what}: holds no cameras")
        empty = [k for k, n in counts.items() if n == 0]
        if empty:
            raise StgsError(f"{self.root / what}: camera {empty[0]} has no frames")
        if len(set(counts.values())) > 1:
            first, odd = next(iter(counts)), next(k for k, n in counts.items() if n != next(iter(counts.values())))
            raise StgsError(f"{self.root / what}: camera {odd} has {counts[odd]} frames, {first} has "
                            f"{counts[first]} (every camera needs the same frames; `stgs prepare` trims videos "
                            "to their common span)")
        return next(iter(counts.values()))

    def _models(self) -> list[ColmapModel]:
        if self.layout == "frames":
            dirs = frame_dirs(self.root)
            own = [d / "sparse" / "0" for d in dirs]
            if all(find_model(p) for p in own):
                return [read_model(p) for p in own]
            for folder in (own[0], top_model(self.root)):
                if folder is not None and find_model(folder):
                    return [read_model(folder)]
            raise StgsError(f"{self.root}: no COLMAP model in {own[0].relative_to(self.root)} or sparse/0")
        folder = top_model(self.root)
        if folder is None:
            raise StgsError(f"{self.root}: no COLMAP model in sparse/0")
        return [read_model(folder)]

    def _match(self, model: ColmapModel) -> dict[str, tuple[Intrinsics, torch.Tensor]]:
        """Camera name -> (intrinsics, world-to-camera) of `model`, every camera of the capture matched."""
        found: dict[str, tuple[Intrinsics, torch.Tensor]] = {}
        for image in sorted(model.images, key=lambda i: i.name):
            key = camera_key(image.name, self.layout)
            if key not in self.camera_names:
                raise StgsError(f"{model.path}: image {image.name!r} (camera {key}) has no frames in the capture "
                                f"(cameras: {', '.join(self.camera_names)})")
            found.setdefault(key, (model.cameras[image.camera_id], torch.from_numpy(image.viewmat())))
        missing = [c for c in self.camera_names if c not in found]
        if missing:
            raise StgsError(f"{model.path}: camera {missing[0]} has frames but no pose in the model "
                            f"({len(missing)} missing)")
        return found

    def _calibration_at(self, frame: int) -> dict[str, tuple[Intrinsics, torch.Tensor]]:
        if not 0 <= frame < self.num_frames:
            raise StgsError(f"{self.name}: frame {frame} is outside 0..{self.num_frames - 1}")
        return self._calibration[frame if len(self._calibration) > 1 else 0]

    def intrinsics(self, camera: str, frame: int = 0) -> Intrinsics:
        """The camera's calibration as the model gives it (distortion included)."""
        return self._calibration_at(frame)[camera][0]

    # --- the Dataset interface ---

    def cameras(self, frame: int) -> list[Camera]:
        cal = self._calibration_at(frame)
        return [Camera(name, cal[name][0].matrix(), cal[name][1].clone(), cal[name][0].width, cal[name][0].height)
                for name in self.camera_names]

    def pixels(self, frame: int, camera: str) -> np.ndarray:
        if camera not in self.camera_names:
            raise StgsError(f"{self.name}: no camera {camera!r}")
        intr = self._calibration_at(frame)[camera][0]
        if self.layout == "videos":
            video = self._videos[camera]
            folder = self.cache / "videos" / f"{camera}-{source_key(video, intr)}"
            extract_video(video, folder, (intr.width, intr.height), intr.undistort)
            return read_rgb8(folder / f"{frame:05d}.png", (intr.height, intr.width))
        return read_undistorted(self._files[camera][frame], intr, self.cache)

    def image(self, frame: int, camera: str) -> torch.Tensor:
        return torch.from_numpy(self.pixels(frame, camera)).float().div_(255.0)

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        """The view's foreground mask where the capture has one: `frameNNNNNN/masks/<cam>.<ext>` (per-frame),
        `masks/<cam>/<frame>.<ext>` (per-camera folders), any non-zero pixel foreground."""
        if self.layout == "videos" or camera not in self.camera_names:
            return None
        image = self._files[camera][frame]
        folder = image.parent.parent / "masks" if self.layout == "frames" else self.root / "masks" / camera
        path = mask_file(folder, image.stem)
        return None if path is None else read_undistorted_mask(path, self._calibration_at(frame)[camera][0])

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The model's 3D points (float32 positions, colours in [0, 1]) as seeds at `frame`: each frame's own
        model's, or the one model's at frame 0 (the time it was calibrated at); None where there are none."""
        model = self.models[frame] if len(self.models) > 1 else (self.models[0] if frame == 0 else None)
        if model is None or not len(model.points):
            return None
        return torch.from_numpy(model.points).float(), torch.from_numpy(model.colours).float() / 255.0

    def check_views(self, frames: list[int], cameras: list[str]) -> None:
        """Every image file of the views at its camera's calibrated size, from the headers (a video's frames are
        scaled to it as they are decoded)."""
        if self.layout == "videos":
            return
        check_image_sizes(self.root, [(self._files[c][f], (self.intrinsics(c, f).width, self.intrinsics(c, f).height))
                                      for f in frames for c in cameras])
