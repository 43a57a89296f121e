"""Where the Gaussians start: triangulated points at a few frames, the rig's walls and floor, jittered copies
and random frustum points up to the capacity (`initial_points`), and the 3DGS-style attributes they get
(`init_canonical`). The geometry is in stgs.train.triangulate."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from scipy.spatial import cKDTree

from stgs.camera import Camera, surrounds
from stgs.data import Dataset
from stgs.model.gop import GOPModel
from stgs.train.hull import HullConfig, hull_surface_points
from stgs.train.triangulate import (
    BACKGROUND_MATCHING,
    MIN_TRIANGULATED,
    background_shell_points,
    ground_height,
    random_frustum_points,
    triangulate,
)

REGIONS = ("foreground", "background")
"""Where initial_points triangulates: where the people are (the dataset's masks), or outside them."""


@dataclass
class InitialPoints:
    """Where the Gaussians start."""

    points: torch.Tensor
    """(N, 3) positions."""
    colors: torch.Tensor
    """(N, 3) colours."""
    anchored: torch.Tensor
    """(N,) bool: seen in the images (triangulated or on the rig's walls and floor) rather than filler
    (jittered copies, random points), which starts fainter so it cannot veil the scene."""
    triangulated: int
    """How many points triangulated."""
    background: int = 0
    """How many points went on the rig's walls and floor."""


def initial_points(ds: Dataset, names: list[str], frames: list[int], count: int, gen: torch.Generator,
                   limit: int = 0, background_share: float = 0.0, hull: HullConfig | None = None,
                   region: str = "foreground") -> InitialPoints:
    """`count` starting points, triangulated at each of `frames` (people who move are seeded where they are
    at each of those times), or the dataset's own points at a frame where it has them (Dataset.points);
    `background_share` of them on the rig's walls and floor (background_shell_points) when the cameras surround
    the scene; with `hull`, where the dataset has every camera's foreground mask at a frame and the cameras
    surround the scene, the capacity left after those goes to points on the surface of the masks' visual hull
    (stgs.train.hull) before any filler. `region` "background": triangulate outside the dataset's foreground
    masks instead (BACKGROUND_MATCHING; the whole image where it has none), for a static layer."""
    if region not in REGIONS:
        raise ValueError(f"region must be one of {', '.join(REGIONS)}, got {region!r}")
    cams, images = _training_views(ds, names, frames[0])  # the walls and floor are coloured from the first frame
    found_at, hull_at = [], []
    for i, frame in enumerate(frames):  # one more frame's images held at a time
        at_cams, at_images = (cams, images) if i == 0 else _training_views(ds, names, frame)
        masks = [ds.mask(frame, c.name) for c in at_cams]
        given = ds.points(frame)  # the capture's own reconstruction (a COLMAP model's points3D) where it has one
        if given is not None:
            found_at.append(given)
        elif region == "background":
            found_at.append(triangulate(at_cams, at_images, [None if m is None else ~m for m in masks],
                                        BACKGROUND_MATCHING))
        else:
            found_at.append(triangulate(at_cams, at_images, masks))
        known = [m for m in masks if m is not None]
        if hull is not None and len(known) == len(masks) and surrounds(at_cams):
            hull_at.append(hull_surface_points(at_cams, at_images, known, hull))
    # A time with too few points to describe the scene there (tiny images, no texture) contributes none: a few
    # points from each of several such times would draw every seeded copy around them instead of random points.
    found_at = [(p, c) for p, c in found_at if len(p) >= MIN_TRIANGULATED]
    pts = torch.cat([p for p, _ in found_at]) if found_at else torch.empty(0, 3)
    col = torch.cat([c for _, c in found_at]) if found_at else torch.empty(0, 3)
    if limit and len(pts) > limit:
        keep = torch.randperm(len(pts), generator=gen)[:limit]
        pts, col = pts[keep], col[keep]
    if len(pts) < MIN_TRIANGULATED:  # random points instead
        pts, col = pts[:0], col[:0]
    found = len(pts)
    parts, colors, background = [], [], 0
    if background_share and surrounds(cams):
        shell, shell_col = background_shell_points(cams, images, int(count * background_share), gen,
                                                   ground_height(cams, pts))
        parts.append(shell)
        colors.append(shell_col)
        count -= len(shell)
        background = len(shell)
    if found >= count:
        keep = torch.randperm(found, generator=gen)[:count]
        pts, col = pts[keep], col[keep]
    parts.append(pts)
    colors.append(col)
    hull_points = sum(len(p) for p, _ in hull_at)
    if hull_points and count > len(pts):
        keep = torch.randperm(hull_points, generator=gen)[:count - len(pts)]
        parts.append(torch.cat([p for p, _ in hull_at])[keep])
        colors.append(torch.cat([c for _, c in hull_at])[keep])
        count -= len(keep)
    anchored = sum(len(p) for p in parts)
    extra_random = (count - len(pts)) // 2 if found else count - len(pts)
    jitter_n = count - len(pts) - extra_random
    if jitter_n:
        src = torch.randint(found, (jitter_n,), generator=gen)
        spread = (pts.std(0) * 0.02).clamp_min(1e-3)
        parts.append(pts[src] + torch.randn(jitter_n, 3, generator=gen) * spread)
        colors.append(col[src])
    if extra_random:
        parts.append(random_frustum_points(cams, extra_random, gen))
        colors.append(torch.rand(extra_random, 3, generator=gen))
    points = torch.cat(parts)
    flags = torch.arange(len(points)) < anchored
    return InitialPoints(points, torch.cat(colors), flags, found, background)


def _training_views(ds: Dataset, names: list[str], frame: int) -> tuple[list[Camera], list[torch.Tensor]]:
    cams = [c for c in ds.cameras(frame) if c.name in names]
    return cams, [ds.image(frame, c.name) for c in cams]


def mean_neighbour_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(N,) float32: each point's mean distance to its k nearest other points (fewer where N <= k; 1 for a lone
    point). A k-d tree, so memory grows with N, not N² (a full distance matrix of 150,000 points is 90 GB)."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
    if not torch.isfinite(points).all():
        raise ValueError("points must be finite")
    n = len(points)
    if n < 2:
        return torch.ones(n)
    xyz = points.detach().double().numpy()
    # The k + 1 nearest of each point include itself at distance 0 (first, or beside an equal duplicate).
    distances, _ = cKDTree(xyz).query(xyz, k=min(k, n - 1) + 1)
    return torch.from_numpy(distances[:, 1:].mean(1)).float()


def init_canonical(model: GOPModel, init: InitialPoints, opacity: float = 0.1, filler_opacity: float = 0.02) -> None:
    """3DGS-style initial attributes: scale from the mean distance to the 3 nearest points."""
    points = init.points
    with torch.no_grad():
        model.xyz.copy_(points)
        nn3 = mean_neighbour_distance(points)
        model.log_scale.copy_(torch.log(nn3.clamp(1e-4, 1e2))[:, None].expand(-1, 3))
        model.rotation.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]))
        start = torch.where(init.anchored, opacity, filler_opacity)
        model.opacity_logit.copy_(torch.log(start / (1 - start)))
        model.color.copy_(init.colors.clamp(0, 1))
        model.features.zero_()
