"""Training views: the images of some frames at the training scale (uint8), their cameras, the scene's extent."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import torch
from tqdm import tqdm

from stgs.camera import Camera, resize
from stgs.data import Dataset
from stgs.errors import StgsError


@dataclass
class Views:
    """Training images of some frames (kept as uint8: a quarter of float32) and their cameras."""

    cameras: list[Camera]
    frames: list[int]
    images: torch.Tensor
    """(F, C, H, W, 3) uint8."""
    dynamic: torch.Tensor | None = None
    """Bool dynamic-pixel masks: (C, H, W), one per camera, or (F, C, H, W), one per view."""

    def target(self, f: int, c: int) -> torch.Tensor:
        return self.images[f, c].float().div_(255.0)

    def dynamic_pixels(self, f: int, c: int) -> torch.Tensor | None:
        """(H, W) the dynamic pixels of view (f, c), or None without masks."""
        if self.dynamic is None:
            return None
        return self.dynamic[f, c] if self.dynamic.ndim == 4 else self.dynamic[c]


def scale_camera(cam: Camera, scale: float) -> Camera:
    """The camera at `scale` times its image size (the training resolution)."""
    return resize(cam, max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))


def load_views(ds: Dataset, names: list[str], frames: list[int], scale: float, progress: bool) -> Views:
    by_name = {c.name: c for c in ds.cameras(frames[0])}
    cams = [scale_camera(by_name[n], scale) for n in names]
    h, w = cams[0].height, cams[0].width
    if any((c.height, c.width) != (h, w) for c in cams):
        raise StgsError(f"{ds.name}: training cameras must share one image size")
    images = torch.empty(len(frames), len(cams), h, w, 3, dtype=torch.uint8)
    for i, f in enumerate(tqdm(frames, desc="load frames", unit="frame", disable=not progress)):
        for j, cam in enumerate(cams):
            img = ds.image(f, cam.name)
            if img.shape[:2] != (h, w):
                img = torch.from_numpy(cv2.resize(img.numpy(), (w, h), interpolation=cv2.INTER_AREA))
            images[i, j] = (img * 255 + 0.5).clamp(0, 255).to(torch.uint8)
    return Views(cams, frames, images)


LOW_RES = 0.5
"""Image scale of a stage's first iterations (TrainConfig.coarse_low_res, TrainConfig.gop_low_res)."""


def downscaled(views: Views, factor: float, moving: torch.Tensor | None = None
               ) -> tuple[Views, torch.Tensor | None]:
    """`views` at `factor` x their image size (area-averaged images, cameras resized), and `moving` (bool masks
    of their pixels, per view (F, C, H, W) or per camera (C, H, W)) with them: a smaller pixel is moving when any
    of the pixels it averages is. The small views carry no masks of their own."""
    cams = [scale_camera(c, factor) for c in views.cameras]
    w, h = cams[0].width, cams[0].height
    f, c = views.images.shape[:2]
    images = torch.empty(f, c, h, w, 3, dtype=torch.uint8)
    for i in range(f):
        for j in range(c):
            images[i, j] = torch.from_numpy(cv2.resize(views.images[i, j].numpy(), (w, h),
                                                       interpolation=cv2.INTER_AREA))
    small = None
    if moving is not None:
        flat = moving.reshape(-1, *moving.shape[-2:])
        small = torch.empty(flat.shape[0], h, w, dtype=torch.bool)
        for k, mask in enumerate(flat):
            area = cv2.resize(mask.numpy().astype("float32"), (w, h), interpolation=cv2.INTER_AREA)
            small[k] = torch.from_numpy(area > 0)
        small = small.reshape(*moving.shape[:-2], h, w)
    return Views(cams, views.frames, images), small


def scene_extent(cams: list[Camera]) -> float:
    centres = torch.stack([c.center for c in cams])
    return float((centres - centres.mean(0)).norm(dim=1).max()) * 1.1 + 1e-6
