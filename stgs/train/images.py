"""Training views: the images of some frames and cameras at the training scale, read through a bounded cache.

Nothing holds a capture's frames: a stage opens the views it draws from (`open_views`) over a `PlannedCache`
whose budget is TrainConfig.max_memory, gives it the draws it will make (`view_draws`, fixed by the run's seed
and the stage, never by the budget) and the cache decodes ahead in a background thread, at the training scale
(level 0) and at LOW_RES of it (level 1), with each view's moving-pixel mask where the stage has masks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np
import torch

from stgs.camera import Camera, resize
from stgs.data import Dataset
from stgs.errors import StgsError
from stgs.memory import physical_memory
from stgs.train.config import stage_seed
from stgs.train.viewcache import PlannedCache

LOW_RES = 0.5
"""Image scale of a stage's first iterations (TrainConfig.coarse_low_res, TrainConfig.gop_low_res): level 1."""
MEMORY_SHARE = 16
"""The view cache's default budget is the machine's RAM over this, at most DEFAULT_MEMORY_CAP."""
DEFAULT_MEMORY_CAP = 1 << 30


def default_memory() -> int:
    """Bytes of decoded views a run holds unless told (TrainConfig.max_memory None): RAM / 16, at most 1 GiB
    (1 GiB where the OS does not say)."""
    ram = physical_memory()
    return DEFAULT_MEMORY_CAP if ram is None else min(DEFAULT_MEMORY_CAP, ram // MEMORY_SHARE)


MaskSource = Callable[[int, int], "np.ndarray | None"]
"""(frame, camera position) -> that view's (H, W) bool moving-pixel mask at the training scale, or None."""


class ViewKey(NamedTuple):
    frame: int
    """Position in the views' frames."""
    camera: int
    """Position in the cache's cameras."""
    level: int
    """0: the training scale; 1: LOW_RES of it."""


class Sample(NamedTuple):
    """One drawn view: where it is, its camera (at the drawn level), its pixels and its moving pixels."""

    frame: int
    camera: int
    cam: Camera
    target: torch.Tensor
    """(H, W, 3) float32 in [0, 1]."""
    dynamic: torch.Tensor | None
    """(H, W) bool, or None without masks."""


def scale_camera(cam: Camera, scale: float) -> Camera:
    """The camera at `scale` times its image size (the training resolution)."""
    return resize(cam, max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))


def quantised(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """A dataset view ((H, W, 3) uint8) at (width, height): itself at its own size, else area-averaged in float
    and rounded back to uint8."""
    if pixels.shape[:2] == (height, width):
        return pixels
    img = cv2.resize(pixels.astype(np.float32) / 255, (width, height), interpolation=cv2.INTER_AREA)
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


def smaller(image: np.ndarray, mask: np.ndarray | None, width: int, height: int
            ) -> tuple[np.ndarray, np.ndarray | None]:
    """A view at (width, height): its pixels area-averaged, a smaller pixel moving when any it averages moves."""
    small = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    if mask is not None:
        mask = cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) > 0
    return small, mask


class ViewSource:
    """Decoded views of `frames` x `cameras` (training-scale cameras), each at level 0 or 1, within `budget`
    bytes: what a PlannedCache loads."""

    def __init__(self, ds: Dataset | None, cameras: list[Camera], frames: list[int], budget: int,
                 masks: MaskSource | None = None, decode: Callable[[int, int], np.ndarray] | None = None):
        self.ds, self.frames, self.masks = ds, list(frames), masks
        self.levels = [list(cameras), [scale_camera(c, LOW_RES) for c in cameras]]
        self._decode = decode or self._from_dataset
        self.cache: PlannedCache[ViewKey, tuple[torch.Tensor, torch.Tensor | None]] = \
            PlannedCache(self._load, self._bytes, budget)

    def _from_dataset(self, f: int, c: int) -> np.ndarray:
        cam = self.levels[0][c]
        if self.ds is None:
            raise ValueError("these views decode from their own function, not a dataset")
        return quantised(self.ds.pixels(self.frames[f], cam.name), cam.width, cam.height)

    def _bytes(self, key: ViewKey) -> int:
        cam = self.levels[key.level][key.camera]
        return cam.width * cam.height * (4 if self.masks is not None else 3)

    def _load(self, key: ViewKey) -> tuple[torch.Tensor, torch.Tensor | None]:
        image = self._decode(key.frame, key.camera)
        mask = self.masks(self.frames[key.frame], key.camera) if self.masks is not None else None
        if key.level:
            cam = self.levels[key.level][key.camera]
            image, mask = smaller(image, mask, cam.width, cam.height)
        return torch.from_numpy(image), torch.from_numpy(mask) if mask is not None else None

    def decoded(self, f: int, c: int) -> np.ndarray:
        """View (f, c)'s (H, W, 3) uint8 pixels at level 0, decoded now and not kept."""
        return self._decode(f, c)

    def set_masks(self, masks: MaskSource | None) -> None:
        """Draw the views with `masks` from now on (what the cache holds is dropped)."""
        self.cache.close()
        self.masks = masks

    def close(self) -> None:
        self.cache.close()


@dataclass
class Views:
    """Some cameras of a ViewSource at one level: `target(f, c)` and `dynamic_pixels(f, c)` by position in
    `frames` and `cameras`."""

    source: ViewSource
    positions: list[int]
    """The cameras' positions in the source."""
    level: int = 0

    @property
    def cameras(self) -> list[Camera]:
        return [self.source.levels[self.level][p] for p in self.positions]

    @property
    def frames(self) -> list[int]:
        return self.source.frames

    @property
    def counts(self) -> tuple[int, int]:
        """(frames, cameras): what `view_draws` draws over."""
        return len(self.source.frames), len(self.positions)

    @property
    def masked(self) -> bool:
        return self.source.masks is not None

    def _get(self, f: int, c: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        return self.source.cache.get(ViewKey(f, self.positions[c], self.level))

    def target(self, f: int, c: int) -> torch.Tensor:
        return self._get(f, c)[0].float().div_(255.0)

    def dynamic_pixels(self, f: int, c: int) -> torch.Tensor | None:
        """(H, W) the moving pixels of view (f, c), or None without masks."""
        return self._get(f, c)[1]

    def decoded(self, f: int, c: int) -> torch.Tensor:
        """`target(f, c)` at level 0 decoded now, outside the cache (a pass over every view)."""
        return torch.from_numpy(self.source.decoded(f, self.positions[c])).float().div_(255.0)

    def sample(self, f: int, c: int) -> Sample:
        image, mask = self._get(f, c)
        return Sample(f, c, self.cameras[c], image.float().div_(255.0), mask)

    def set_masks(self, masks: MaskSource | None) -> None:
        """Draw these cameras' views with `masks` (by camera position here); the source's other cameras' have
        none."""
        if masks is None:
            self.source.set_masks(None)
            return
        here = {p: c for c, p in enumerate(self.positions)}
        self.source.set_masks(lambda frame, p: masks(frame, here[p]) if p in here else None)

    def at(self, level: int) -> Views:
        return replace(self, level=level)

    def plan(self, draws: list[tuple[int, int, int]]) -> None:
        """The (frame, camera, level) draws to come, in order: the cache decodes them ahead."""
        self.source.cache.plan([ViewKey(f, self.positions[c], level) for f, c, level in draws])

    def close(self) -> None:
        self.source.close()


def open_views(ds: Dataset, names: list[str], frames: list[int], scale: float, budget: int,
               holdout: list[str] | None = None) -> tuple[Views, Views | None]:
    """The views of cameras `names` (and `holdout`'s, sharing the cache) over `frames`, at `scale`, within
    `budget` bytes; masks come later (Views.set_masks)."""
    by_name = {c.name: c for c in ds.cameras(frames[0])}
    every = list(names) + list(holdout or [])
    cams = [scale_camera(by_name[n], scale) for n in every]
    if any((c.height, c.width) != (cams[0].height, cams[0].width) for c in cams[: len(names)]):
        raise StgsError(f"{ds.name}: training cameras must share one image size")
    trained = len(names)
    source = ViewSource(ds, cams, frames, budget)
    views = Views(source, list(range(trained)))
    return views, Views(source, list(range(trained, len(every)))) if holdout else None


def tensor_views(cameras: list[Camera], frames: list[int], images: torch.Tensor,
                 dynamic: torch.Tensor | None = None, budget: int = 1 << 62) -> Views:
    """Views of (F, C, H, W, 3) uint8 `images` held in memory, with masks (F, C, H, W) per view or (C, H, W) per
    camera: for tests and tools that make their own images."""
    source = ViewSource(None, cameras, frames, budget, decode=lambda f, c: images[f, c].numpy())
    views = Views(source, list(range(len(cameras))))
    if dynamic is not None:
        views.set_masks(lambda frame, c: (dynamic[frames.index(frame), c] if dynamic.ndim == 4 else dynamic[c]).numpy())
    return views


def view_draws(seed: int, stage: str, iterations: int, frames: int, cameras: int, low_until: int = 0
               ) -> list[tuple[int, int, int]]:
    """The (frame, camera, level) each iteration of `stage` draws: uniform over the frames and cameras, from a
    generator of their own (seeded by the run's seed and the stage), so that the cache knows them ahead and no
    other draw (noise, dropped Gaussians, relocation) shifts them; level 1 before iteration `low_until`."""
    gen = torch.Generator().manual_seed(stage_seed(seed, f"{stage}/views"))
    f = torch.randint(frames, (iterations,), generator=gen).tolist()
    c = torch.randint(cameras, (iterations,), generator=gen).tolist()
    return [(f[i], c[i], int(i < low_until)) for i in range(iterations)]

