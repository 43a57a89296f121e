"""Seeds on the moving people from the dataset's foreground masks: the surface of their visual hull.

SIFT triangulation (stgs.train.triangulate) finds a few hundred points per frame on the people, where their clothes
have texture, and none on a ball or a plain shirt. A rig that surrounds the action with calibrated cameras and
has foreground masks pins the people down better: a point of space belongs to them when every camera that sees
it sees a foreground pixel there (space carving). `hull_surface_points` carves a voxel grid around the rig's
focus, coarse then fine, keeps the hull's surface voxels and colours each from the cameras on its outer side.

Mask errors (a limb a camera's mask misses) would carve the person away, so a voxel survives up to
`max_misses` cameras that see background there; it must be seen by at least `min_views` cameras.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from stgs.camera import Camera, rig_focus
from stgs.train.triangulate import in_view

_COARSE_FACTOR = 2
"""The coarse pass's voxels are this many fine voxels wide."""
MAX_FINE_SIDE = 512
"""Most fine voxels along one side of the carved box (about 205 by default)."""


@dataclass
class HullConfig:
    """Settings of the carving."""

    voxel: float = 1 / 128
    """Fine voxel edge, as a share of the cameras' mean distance from the rig's focus."""
    extent: float = 0.8
    """Half-width of the carved box around the focus, as the same share."""
    min_views: int = 4
    """Cameras that must see a voxel."""
    max_misses: int = 1
    """Cameras that see it may put it on background pixels (mask errors) before it is carved away."""
    facing: float = 0.2
    """A camera colours a surface voxel when the cosine between the voxel's outward normal and the direction
    to the camera exceeds this."""

    def __post_init__(self) -> None:
        if not (self.voxel > 0 and self.extent > 0 and self.min_views >= 1 and self.max_misses >= 0):
            raise ValueError("hull: voxel and extent must be > 0, min_views >= 1 and max_misses >= 0")
        if 2 * self.extent / self.voxel > MAX_FINE_SIDE:  # the grids (bool and float32) grow with its cube
            raise ValueError(f"hull: extent / voxel gives a grid of more than {MAX_FINE_SIDE} voxels a side")


def _pixels(cam: Camera, mask: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P,) bool whether `cam` sees each point, and its (P,) pixel column and row (clipped to the image)."""
    uv, inside = in_view(cam, points)
    h, w = mask.shape
    return inside, np.clip(uv[:, 0].astype(np.int64), 0, w - 1), np.clip(uv[:, 1].astype(np.int64), 0, h - 1)


def _carve(points: np.ndarray, cameras: list[Camera], masks: list[np.ndarray], cfg: HullConfig) -> np.ndarray:
    """(P,) bool: the points inside the visual hull."""
    seen = np.zeros(len(points), np.int32)
    misses = np.zeros(len(points), np.int32)
    for cam, mask in zip(cameras, masks, strict=True):
        inside, x, y = _pixels(cam, mask, points)
        seen += inside
        misses += inside & ~mask[y, x]
    return (seen >= cfg.min_views) & (misses <= cfg.max_misses)


def _grid(lo: np.ndarray, step: float, shape: tuple[int, ...]) -> np.ndarray:
    """(prod(shape), 3) centres of the voxels of a box from `lo`."""
    axes = [lo[k] + (np.arange(shape[k]) + 0.5) * step for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def hull_voxels(cameras: list[Camera], masks: list[np.ndarray], cfg: HullConfig) -> tuple[np.ndarray, np.ndarray,
                                                                                              float]:
    """The fine occupancy grid of the visual hull: (X, Y, Z) bool, its origin and its voxel edge."""
    focus, rig = rig_focus(cameras)
    fine = cfg.voxel * rig
    coarse = fine * _COARSE_FACTOR
    half = cfg.extent * rig
    n = int(np.ceil(2 * half / coarse))
    lo = focus.numpy() - n * coarse / 2
    occupied = _carve(_grid(lo, coarse, (n, n, n)), cameras, masks, cfg).reshape(n, n, n)
    # A fine voxel can be in the hull while its coarse parent's centre is not: test the children of the
    # coarse hull grown by one voxel.
    parents = ndimage.binary_dilation(occupied)
    fine_occupied = np.zeros((n * _COARSE_FACTOR,) * 3, bool)
    if not parents.any():
        return fine_occupied, lo, fine
    cells = np.repeat(np.repeat(np.repeat(parents, _COARSE_FACTOR, 0), _COARSE_FACTOR, 1), _COARSE_FACTOR, 2)
    index = np.argwhere(cells)
    centres = lo + (index + 0.5) * fine
    fine_occupied[tuple(index.T)] = _carve(centres, cameras, masks, cfg)
    return fine_occupied, lo, fine


def hull_surface_points(cameras: list[Camera], images: list[torch.Tensor], masks: list[torch.Tensor],
                        cfg: HullConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, 3) points on the surface of the masks' visual hull and (P, 3) colours: the median of the foreground
    pixels they land on in the cameras on their outer side (every camera that sees them when none faces them)."""
    cfg = cfg or HullConfig()
    if len(cameras) != len(masks) or len(cameras) != len(images):
        raise ValueError(f"hull: {len(cameras)} cameras, {len(images)} images and {len(masks)} masks")
    mask_arrays = [m.numpy().astype(bool) for m in masks]
    occupied, lo, step = hull_voxels(cameras, mask_arrays, cfg)
    surface = occupied & ~ndimage.binary_erosion(occupied)
    index = np.argwhere(surface)
    if len(index) == 0:
        return torch.empty(0, 3), torch.empty(0, 3)
    points = lo + (index + 0.5) * step
    # Outward normal: down the gradient of the smoothed occupancy.
    smooth = ndimage.gaussian_filter(occupied.astype(np.float32), 1.5)
    grad = np.stack([np.gradient(smooth, axis=k)[tuple(index.T)] for k in range(3)], 1)
    normal = -grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
    samples = np.full((len(points), len(cameras), 3), np.nan, np.float32)
    facing = np.zeros((len(points), len(cameras)), bool)
    for k, (cam, img, mask) in enumerate(zip(cameras, images, mask_arrays, strict=True)):
        inside, x, y = _pixels(cam, mask, points)
        ok = inside & mask[y, x]
        samples[ok, k] = img.numpy()[y[ok], x[ok]]
        to_cam = cam.center.numpy() - points
        cosine = (to_cam * normal).sum(1) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-9)
        facing[:, k] = ok & (cosine > cfg.facing)
    any_facing = facing.any(1)
    colors = np.where(facing[:, :, None], samples, np.nan)
    colors[~any_facing] = samples[~any_facing]
    seen = ~np.isnan(colors[:, :, 0]).all(1)
    colors = np.nanmedian(colors[seen], axis=1)
    return torch.from_numpy(points[seen]).float(), torch.from_numpy(colors).float().clamp(0, 1)
