"""The Panoptic / Dynamic 3D Gaussians layout (docs/CAPTURE.md; the development capture is
`../shared/data/panoptic-basketball`).

`train_meta.json`: w, h, k[frame][cam] (3x3), w2c[frame][cam] (4x4,
world-to-camera, OpenCV axes), fn[frame][cam] (`<cam>/<frame>.jpg` under
`ims/`), cam_id[frame][cam]; foreground masks `seg/<cam>/<frame>.png`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera
from stgs.data.images import check_image_sizes, read_mask, read_rgb8
from stgs.errors import StgsError

META = "train_meta.json"
FPS = 30.0
"""Panoptic's HD cameras run at 29.97 fps; Dynamic 3D Gaussians treats it as 30."""


class PanopticReader:
    def __init__(self, root: Path, holdout: list[str] | None = None):
        self.root = Path(root)
        self.name = f"panoptic:{self.root.name}"
        self.fps = FPS
        try:
            meta = json.loads((self.root / META).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise StgsError(f"{self.root}: cannot read {META} ({exc})") from None
        try:
            self.width, self.height = int(meta["w"]), int(meta["h"])
            k, w2c, fn, ids = meta["k"], meta["w2c"], meta["fn"], meta["cam_id"]
        except (KeyError, TypeError, ValueError) as exc:
            raise StgsError(f"{self.root / META}: missing or malformed key ({exc})") from None
        frames = len(fn)
        if not frames or not (len(k) == len(w2c) == len(ids) == frames):
            raise StgsError(f"{self.root / META}: k, w2c, fn and cam_id list {len(k)}, {len(w2c)}, {frames} and "
                            f"{len(ids)} frames; they must agree (and not be empty)")
        counts = {len(x) for f in range(frames) for x in (k[f], w2c[f], fn[f], ids[f])}
        if len(counts) != 1:
            raise StgsError(f"{self.root / META}: camera counts differ between frames or keys ({sorted(counts)})")
        if any(ids[f] != ids[0] for f in range(frames)):
            raise StgsError(f"{self.root / META}: cameras are listed in a different order in some frames")
        self.num_frames = frames
        self.camera_names = [str(c) for c in ids[0]]
        self.default_holdout = list(holdout or [])
        self._k = torch.tensor(k, dtype=torch.float64)
        self._w2c = torch.tensor(w2c, dtype=torch.float64)
        if self._k.shape[2:] != (3, 3) or self._w2c.shape[2:] != (4, 4):
            raise StgsError(f"{self.root / META}: k must be 3x3 and w2c 4x4 per camera")
        self._fn = fn
        missing = [f"ims/{name}" for row in fn for name in row if not (self.root / "ims" / name).is_file()]
        if missing:
            raise StgsError(f"{self.root}: {len(missing)} frame image(s) missing, e.g. {missing[0]}")

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (Path(path) / META).is_file()

    def cameras(self, frame: int) -> list[Camera]:
        return [Camera(name, self._k[frame, c], self._w2c[frame, c], self.width, self.height)
                for c, name in enumerate(self.camera_names)]

    def _file(self, frame: int, camera: str) -> str:
        try:
            return self._fn[frame][self.camera_names.index(camera)]
        except (IndexError, ValueError):
            raise StgsError(f"{self.name}: no frame {frame} of camera {camera!r}") from None

    def image(self, frame: int, camera: str) -> torch.Tensor:
        return torch.from_numpy(self.pixels(frame, camera)).float().div_(255.0)

    def pixels(self, frame: int, camera: str) -> np.ndarray:
        return read_rgb8(self.root / "ims" / self._file(frame, camera), (self.height, self.width))

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        path = self.root / "seg" / Path(self._file(frame, camera)).with_suffix(".png")
        return read_mask(path, (self.height, self.width)) if path.is_file() else None

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None

    def check_views(self, frames: list[int], cameras: list[str]) -> None:
        """Every image (and mask, where there is one) of the views at the meta's size, from the headers."""
        size = (self.width, self.height)
        names = [self._file(frame, camera) for frame in frames for camera in cameras]
        masks = (self.root / "seg" / Path(name).with_suffix(".png") for name in names)
        check_image_sizes(self.root, [(self.root / "ims" / name, size) for name in names]
                          + [(mask, size) for mask in masks if mask.is_file()])
