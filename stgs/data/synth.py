"""The ground truth inside a `stgs synth` model dir, read as a multi-view dataset."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from stgs.camera import Camera
from stgs.data.images import check_image_sizes, read_mask, read_rgb8
from stgs.errors import StgsError
from stgs.synth import load_ground_truth
from stgs.tree import CAMERAS, GROUND_TRUTH_DIR, MASKS_DIR


class SynthReader:
    def __init__(self, root: Path, holdout: list[str] | None = None):
        self.root = Path(root)
        self.name = f"synth:{self.root.name}"
        try:
            doc, cams = load_ground_truth(self.root)
            self.fps, self.num_frames, self.pattern = float(doc["fps"]), int(doc["num_frames"]), str(doc["pattern"])
        except (KeyError, TypeError, ValueError) as exc:
            raise StgsError(f"{self.root}: malformed {GROUND_TRUTH_DIR}/{CAMERAS} ({exc})") from None
        self._cameras = cams
        self.camera_names = [c.name for c in cams]
        self.default_holdout = list(holdout) if holdout is not None else self.camera_names[-1:][: len(cams) - 1]

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return (Path(path) / GROUND_TRUTH_DIR / CAMERAS).is_file()

    def cameras(self, frame: int) -> list[Camera]:
        return list(self._cameras)

    def image(self, frame: int, camera: str) -> torch.Tensor:
        return torch.from_numpy(self.pixels(frame, camera)).float().div_(255.0)

    def pixels(self, frame: int, camera: str) -> np.ndarray:
        cam = next((c for c in self._cameras if c.name == camera), None)
        if cam is None or not 0 <= frame < self.num_frames:
            raise StgsError(f"{self.name}: no frame {frame} of camera {camera!r}")
        return read_rgb8(self.root / GROUND_TRUTH_DIR / self.pattern.format(camera=camera, frame=frame),
                         (cam.height, cam.width))

    def mask(self, frame: int, camera: str) -> torch.Tensor | None:
        """The foreground mask `stgs synth` wrote (None for a scene written before it wrote masks)."""
        cam = next((c for c in self._cameras if c.name == camera), None)
        if cam is None:
            raise StgsError(f"{self.name}: no camera {camera!r}")
        path = self.root / GROUND_TRUTH_DIR / MASKS_DIR / self.pattern.format(camera=camera, frame=frame)
        return read_mask(path, (cam.height, cam.width)) if path.is_file() else None

    def points(self, frame: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None

    def check_views(self, frames: list[int], cameras: list[str]) -> None:
        """Every ground-truth image (and mask, where there is one) of the views at its camera's size."""
        by_name = {c.name: c for c in self._cameras}
        unknown = sorted(set(cameras) - set(by_name))
        if unknown:
            raise StgsError(f"{self.name}: no camera(s) {unknown}")
        items = []
        for frame in frames:
            for name in cameras:
                size = (by_name[name].width, by_name[name].height)
                rel = self.pattern.format(camera=name, frame=frame)
                items.append((self.root / GROUND_TRUTH_DIR / rel, size))
                mask = self.root / GROUND_TRUTH_DIR / MASKS_DIR / rel
                if mask.is_file():
                    items.append((mask, size))
        check_image_sizes(self.root, items)
