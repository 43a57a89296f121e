"""Initial point cloud from calibrated views: match, triangulate, filter (OpenCV); else random in the frustum.

1. SIFT keypoints per training camera (inside the region mask, grown or
   shrunk, where the dataset has masks: the foreground for the people, its
   complement for the static background), matched between each camera and
   its nearest neighbours: Lowe's ratio test over all keypoints, kept only
   near the epipolar line the known calibration predicts; or, guided, the
   ratio test among the keypoints near that line only, kept when mutual
   (a wall of repeated dots fails the global ratio test everywhere);
2. `cv2.triangulatePoints`, kept when in front of both cameras and
   reprojecting within `max_reprojection_px` in both;
3. multi-view consistency: a point must land inside the image (and the
   region mask) of at least `min_views` cameras with a colour close to
   its own in at least `min_consistent` cameras besides the pair.
If that leaves too few points, `random_frustum_points` fills in. The
background an inward-facing rig sees behind the action (walls, floor, dome)
triangulates only with BACKGROUND_MATCHING's settings (faint, repeated
texture); `background_shell_points` seeds its flat parts on the walls the
cameras hang on (the sphere through them) and on the floor the triangulated
people stand on, coloured from the images.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from stgs.camera import Camera, rig_down, rig_focus

MIN_TRIANGULATED = 32
"""Fewer triangulated points than this do not describe a scene (tiny images, no texture)."""


@dataclass
class InitConfig:
    """Settings of the point-cloud initialisation."""

    neighbours: int = 3
    """Each camera is matched with this many nearest cameras."""
    ratio: float = 0.75
    """Lowe's ratio test threshold."""
    max_epipolar_px: float = 2.0
    """Largest distance of a match to its epipolar line."""
    max_reprojection_px: float = 2.0
    """Largest reprojection error in either camera of the pair."""
    min_views: int = 3
    """Cameras a point must project into (inside the image and the mask)."""
    min_consistent: int = 1
    """Other cameras whose pixel colour must match the point's."""
    color_tolerance: float = 0.12
    """Largest colour difference (mean absolute, [0, 1]) that counts as consistent."""
    max_features: int = 4000
    """SIFT keypoints per image."""
    contrast_threshold: float = 0.04
    """SIFT's contrast threshold (lower: more keypoints on faint texture)."""
    guided: bool = False
    """Match along the epipolar lines (ratio test among the keypoints within max_epipolar_px, mutual best)."""
    region_grow_px: int = 4
    """The region masks are grown by this many pixels before keypoints are sought in them (negative: shrunk)."""


BACKGROUND_MATCHING = InitConfig(neighbours=4, ratio=0.8, contrast_threshold=0.01, guided=True, region_grow_px=-4)
"""Triangulation of a static background (the static layer's seeds): the faint dots, seams and lamps of walls and
floor, outside the foreground masks shrunk by 4 px. On Panoptic's frame 0 it finds about 3,900 points where the
foreground settings outside the masks find about 430 (docs/TRAINING.md)."""


def projection(cam: Camera) -> np.ndarray:
    return (cam.K @ cam.viewmat[:3]).numpy()


def project(cam: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (P, 2) and depths (P,) of world points in a camera."""
    cam_pts = points @ cam.viewmat[:3, :3].numpy().T + cam.viewmat[:3, 3].numpy()
    z = cam_pts[:, 2]
    uv = cam_pts @ cam.K.numpy().T
    return uv[:, :2] / np.where(np.abs(uv[:, 2:]) < 1e-12, 1e-12, uv[:, 2:]), z


def in_view(cam: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (P, 2) of world points and whether each lands in the image in front of the camera."""
    uv, z = project(cam, points)
    return uv, (z > 0.01) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)


def fundamental(a: Camera, b: Camera) -> np.ndarray:
    """F with x_b^T F x_a = 0 from the known calibration."""
    ra, ta = a.viewmat[:3, :3].numpy(), a.viewmat[:3, 3].numpy()
    rb, tb = b.viewmat[:3, :3].numpy(), b.viewmat[:3, 3].numpy()
    r = rb @ ra.T
    t = tb - r @ ta
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(b.K.numpy()).T @ tx @ r @ np.linalg.inv(a.K.numpy())


def _to_gray(image: torch.Tensor) -> np.ndarray:
    return cv2.cvtColor((image.numpy() * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def _sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    x = np.clip(np.round(uv[:, 0] - 0.5).astype(int), 0, w - 1)
    y = np.clip(np.round(uv[:, 1] - 0.5).astype(int), 0, h - 1)
    return image[y, x]


def triangulate(cameras: list[Camera], images: list[torch.Tensor], masks: list[torch.Tensor | None],
                cfg: InitConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, 3) points and (P, 3) colours from calibrated views (see the module docstring)."""
    cfg = cfg or InitConfig()
    sift = cv2.SIFT.create(nfeatures=cfg.max_features, contrastThreshold=cfg.contrast_threshold)
    feats = []
    for img, mask in zip(images, masks, strict=True):
        kps, desc = sift.detectAndCompute(_to_gray(img), None if mask is None else
                                         grown(mask.numpy().astype(np.uint8) * 255, cfg.region_grow_px))
        feats.append((np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2) + 0.5, desc))
    centres = np.stack([c.center.numpy() for c in cameras])
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    points, colors = [], []
    pairs = set()
    for i in range(len(cameras)):
        dist = np.linalg.norm(centres - centres[i], axis=1)
        for j in np.argsort(dist)[1:cfg.neighbours + 1]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    for i, j in sorted(pairs):
        (pi, di), (pj, dj) = feats[i], feats[j]
        if di is None or dj is None or len(di) < 2 or len(dj) < 2:
            continue
        F = fundamental(cameras[i], cameras[j])
        if cfg.guided:
            a_idx, b_idx = guided_matches(pi, di, pj, dj, F, cfg)
        else:
            good = [m for m, n in matcher.knnMatch(di, dj, k=2) if m.distance < cfg.ratio * n.distance]
            a_idx = np.array([m.queryIdx for m in good], dtype=int)
            b_idx = np.array([m.trainIdx for m in good], dtype=int)
            epipolar = np.abs(np.sum(epipolar_lines(pi[a_idx], F) * homogeneous(pj[b_idx]), axis=1))
            keep = epipolar < cfg.max_epipolar_px
            a_idx, b_idx = a_idx[keep], b_idx[keep]
        if not len(a_idx):
            continue
        xa, xb = pi[a_idx], pj[b_idx]
        hom = cv2.triangulatePoints(projection(cameras[i]), projection(cameras[j]), xa.T, xb.T)
        pts = (hom[:3] / np.where(np.abs(hom[3]) < 1e-12, 1e-12, hom[3])).T
        ok = np.ones(len(pts), dtype=bool)
        for cam, x in ((cameras[i], xa), (cameras[j], xb)):
            uv, z = project(cam, pts)
            ok &= (z > 0.01) & (np.linalg.norm(uv - x, axis=1) < cfg.max_reprojection_px)
        col = (_sample(images[i].numpy(), xa[ok]) + _sample(images[j].numpy(), xb[ok])) / 2
        points.append(pts[ok])
        colors.append(col)
    if not points:
        return torch.empty(0, 3), torch.empty(0, 3)
    pts, col = np.concatenate(points), np.concatenate(colors)
    keep = consistent(pts, col, cameras, images, masks, cfg)
    return torch.from_numpy(pts[keep]).float(), torch.from_numpy(col[keep]).float()


def grown(image: np.ndarray, px: int) -> np.ndarray:
    """A uint8 (H, W) mask image grown by `px` pixels with a square kernel (negative: shrunk; 0: as it is)."""
    if px == 0:
        return image
    kernel = np.ones((2 * abs(px) + 1,) * 2, np.uint8)
    return cv2.dilate(image, kernel) if px > 0 else cv2.erode(image, kernel)


def homogeneous(x: np.ndarray) -> np.ndarray:
    return np.c_[x, np.ones(len(x))]


def epipolar_lines(xa: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(P, 3) the lines in image b of the pixels xa (P, 2) of image a (F: x_b^T F x_a = 0), scaled so that a
    line's dot product with a homogeneous pixel is its signed distance in pixels."""
    lines = homogeneous(xa) @ F.T
    return lines / np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-12)[:, None]


def guided_matches(pa: np.ndarray, da: np.ndarray, pb: np.ndarray, db: np.ndarray, F: np.ndarray,
                   cfg: InitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the keypoint pairs matched along the epipolar lines: each keypoint of a against those of b
    within max_epipolar_px of its line, kept when its best passes the ratio test against its second there and
    the two are each other's best."""
    da, db = da.astype(np.float64), db.astype(np.float64)
    distance = np.sqrt(np.maximum((da ** 2).sum(1)[:, None] + (db ** 2).sum(1)[None] - 2 * da @ db.T, 0))
    distance[np.abs(epipolar_lines(pa, F) @ homogeneous(pb).T) > cfg.max_epipolar_px] = np.inf
    if distance.shape[1] < 2:
        return np.empty(0, dtype=int), np.empty(0, dtype=int)
    two = np.partition(distance, 1, axis=1)[:, :2]
    best = np.argmin(distance, axis=1)
    ok = np.isfinite(two[:, 0]) & (two[:, 0] < cfg.ratio * two[:, 1])
    ok &= np.argmin(distance, axis=0)[best] == np.arange(len(pa))
    return np.flatnonzero(ok), best[ok]


def consistent(points: np.ndarray, colors: np.ndarray, cameras: list[Camera], images: list[torch.Tensor],
               masks: list[torch.Tensor | None], cfg: InitConfig) -> np.ndarray:
    """Points seen by min_views cameras and colour-consistent in min_consistent + 2 of them."""
    views = np.zeros(len(points), dtype=int)
    agree = np.zeros(len(points), dtype=int)
    for cam, img, mask in zip(cameras, images, masks, strict=True):
        uv, inside = in_view(cam, points)
        if mask is not None:
            inside &= _sample(mask.numpy(), uv)
        views += inside
        diff = np.abs(_sample(img.numpy(), uv) - colors).mean(axis=1)
        agree += inside & (diff < cfg.color_tolerance)
    return (views >= cfg.min_views) & (agree >= cfg.min_consistent + 2)


def rig_sphere(cameras: list[Camera]) -> tuple[torch.Tensor, float]:
    """Centre and radius of the sphere through the camera centres (least squares); an inward-facing dome rig
    mounts its cameras on its walls, so this is where the walls are. Where the centres do not pin a sphere
    down (a flat ring, a line) or do not lie on one: the rig focus and the cameras' mean distance from it."""
    centres = torch.stack([c.center for c in cameras]).double()
    A = torch.cat([2 * centres, torch.ones(len(centres), 1, dtype=torch.float64)], 1)
    b = (centres ** 2).sum(1, keepdim=True)
    if len(centres) >= 4 and torch.linalg.matrix_rank(A, rtol=1e-6) == 4:
        solution = torch.linalg.lstsq(A, b).solution[:, 0]
        centre = solution[:3]
        radius = float(torch.sqrt((solution[3] + centre @ centre).clamp_min(0)))
        spread = ((centres - centre).norm(dim=1) - radius).abs().max()
        if radius > 0 and spread < 0.1 * radius:
            return centre, radius
    return rig_focus(cameras)


def ground_height(cameras: list[Camera], points: torch.Tensor) -> tuple[torch.Tensor, float] | None:
    """The rig's down direction (the cameras' mean image-down axis) and the floor's height along it: where the
    lowest triangulated points are (people stand on it); None without enough points."""
    if len(points) < MIN_TRIANGULATED:
        return None
    down = rig_down(cameras)
    return down, float(torch.quantile(points.double() @ down, 0.995))


def background_shell_points(cameras: list[Camera], images: list[torch.Tensor], count: int, gen: torch.Generator,
                            ground: tuple[torch.Tensor, float] | None = None, outer: float = 1.08,
                            keep_away: float = 0.3) -> tuple[torch.Tensor, torch.Tensor]:
    """`count` points on the rig's walls (the sphere through the cameras, 1..`outer` × its radius) and, with
    `ground`, its floor (wall points below the floor move onto it along the ray from the centre), that some
    camera sees, none within `keep_away` × the radius of a camera (they would fill its image), each coloured
    with the median of the pixels it lands on."""
    centre, radius = rig_sphere(cameras)
    cam_centres = torch.stack([c.center for c in cameras]).double()
    points, colors, found = [], [], 0
    for _ in range(20):
        if found >= count:
            break
        direction = torch.randn(4 * count, 3, generator=gen, dtype=torch.float64)
        direction /= direction.norm(dim=1, keepdim=True).clamp_min(1e-12)
        shell = radius * (1 + (outer - 1) * torch.rand(4 * count, 1, generator=gen, dtype=torch.float64))
        cand = centre + direction * shell
        if ground is not None:
            down, floor = ground
            height, centre_height = cand @ down, float(centre @ down)
            below = height > floor
            if floor > centre_height:
                t = (floor - centre_height) / (height[below] - centre_height)
                cand[below] = centre + (cand[below] - centre) * t[:, None]
        kept = cand[torch.cdist(cand, cam_centres).min(1).values > keep_away * radius].numpy()
        samples = np.full((len(kept), len(cameras), 3), np.nan)
        for k, (cam, img) in enumerate(zip(cameras, images, strict=True)):
            uv, seen = in_view(cam, kept)
            samples[seen, k] = _sample(img.numpy(), uv[seen])
        seen_any = ~np.isnan(samples[:, :, 0]).all(axis=1)
        points.append(kept[seen_any])
        colors.append(np.nanmedian(samples[seen_any], axis=1))
        found += int(seen_any.sum())
    if found == 0:
        return torch.empty(0, 3), torch.empty(0, 3)
    pts, col = np.concatenate(points)[:count], np.concatenate(colors)[:count]
    return torch.from_numpy(pts).float(), torch.from_numpy(col).float()


def random_frustum_points(cameras: list[Camera], count: int, gen: torch.Generator) -> torch.Tensor:
    """`count` random points in the region most cameras see: around the point nearest every optical axis."""
    focus, rig = rig_focus(cameras)
    radius = rig * 0.35
    out: list[torch.Tensor] = []
    tries = 0
    while sum(len(o) for o in out) < count and tries < 50:
        tries += 1
        cand = focus + (torch.rand(4 * count, 3, generator=gen, dtype=torch.float64) * 2 - 1) * radius
        seen = torch.zeros(len(cand), dtype=torch.long)
        for cam in cameras:
            seen += torch.from_numpy(in_view(cam, cand.numpy())[1])
        out.append(cand[seen >= max(1, len(cameras) // 2)])
    pts = torch.cat(out) if out else torch.empty(0, 3, dtype=torch.float64)
    if len(pts) < count:  # nothing is seen by half the cameras: fall back to the ball itself
        extra = focus + (torch.rand(count - len(pts), 3, generator=gen, dtype=torch.float64) * 2 - 1) * radius
        pts = torch.cat([pts, extra])
    return pts[:count].float()
