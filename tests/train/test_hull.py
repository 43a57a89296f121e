"""Seeds on the visual hull of the foreground masks (stgs.train.hull): a sphere seen by a synthetic rig, and the
Panoptic players checked from the held-out cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stgs.camera import Camera, intrinsics, look_at
from stgs.train.hull import HullConfig, hull_surface_points
from stgs.train.triangulate import in_view
from tests.train.conftest import HELD_OUT, shares_per_point

RADIUS = 0.5
CENTRE = np.array([0.2, -0.1, 0.3])


def _dome(count: int = 16, distance: float = 4.0) -> list[Camera]:
    """Cameras on two rings around CENTRE, looking at it."""
    K = intrinsics(160, 120, 50.0)
    cams = []
    for i in range(count):
        angle = 2 * math.pi * i / count
        elevation = 0.35 if i % 2 else -0.2
        eye = CENTRE + distance * np.array([math.cos(angle) * math.cos(elevation), math.sin(elevation),
                                            math.sin(angle) * math.cos(elevation)])
        cams.append(Camera(f"c{i}", K.clone(), look_at(tuple(eye), tuple(CENTRE)), 160, 120))
    return cams


def _sphere_views(cams: list[Camera]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Per camera, the exact silhouette of the sphere and an image whose pixels are red on the sphere's +x half
    (seen along the pixel's ray) and blue on its -x half."""
    images, masks = [], []
    for cam in cams:
        v, u = np.mgrid[0:cam.height, 0:cam.width] + 0.5
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K.numpy()).T
        rot = cam.viewmat[:3, :3].numpy()
        dirs = rays @ rot  # camera to world: R^T d
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        origin = cam.center.numpy()
        oc = origin - CENTRE
        b = dirs @ oc
        disc = b ** 2 - (oc @ oc - RADIUS ** 2)
        hit = disc > 0
        t = -b - np.sqrt(np.where(hit, disc, 0))
        x = origin[0] + t * dirs[..., 0] - CENTRE[0]
        image = np.zeros((cam.height, cam.width, 3), np.float32)
        image[hit & (x > 0)] = [1, 0, 0]
        image[hit & (x <= 0)] = [0, 0, 1]
        images.append(torch.from_numpy(image))
        masks.append(torch.from_numpy(hit))
    return images, masks


def test_the_hull_of_a_sphere_is_on_its_surface_and_takes_its_colours():
    cams = _dome()
    images, masks = _sphere_views(cams)
    pts, colors = hull_surface_points(cams, images, masks, HullConfig(voxel=1 / 64, max_misses=0))
    assert len(pts) > 500 and colors.shape == pts.shape
    r = (pts.double().numpy() - CENTRE) / RADIUS
    dist = np.linalg.norm(r, axis=1)
    # A hull from 16 views is a little larger than the sphere (by at most the polygon's corner, ~4 % here)
    # and its surface voxels are within one voxel (0.0625 units: 0.125 R at voxel 1/64 of a 4-unit rig) of it.
    assert np.median(dist) == pytest.approx(1.0, abs=0.06) and dist.min() > 0.8 and dist.max() < 1.2
    side = r[:, 0]
    clear = np.abs(side) > 0.3  # far from the colour boundary
    red = colors[:, 0].numpy() > 0.5
    assert (red[clear] == (side[clear] > 0)).mean() > 0.97


def test_mask_errors_are_survived_up_to_max_misses():
    cams = _dome()
    images, masks = _sphere_views(cams)
    masks[3] = torch.zeros_like(masks[3])  # one camera's mask lost the object
    tolerant, _ = hull_surface_points(cams, images, masks, HullConfig(voxel=1 / 64, max_misses=1))
    strict, _ = hull_surface_points(cams, images, masks, HullConfig(voxel=1 / 64, max_misses=0))
    assert len(tolerant) > 500 and len(strict) == 0


def test_no_foreground_gives_no_points():
    cams = _dome(8)
    images, masks = _sphere_views(cams)
    pts, colors = hull_surface_points(cams, images, [torch.zeros_like(m) for m in masks])
    assert pts.shape == (0, 3) and colors.shape == (0, 3)
    with pytest.raises(ValueError, match="masks"):
        hull_surface_points(cams, images, masks[:-1])
    for bad in ({"voxel": 0.0}, {"extent": -1.0}, {"min_views": 0}, {"max_misses": -1}, {"voxel": 1e-4}):
        with pytest.raises(ValueError, match="hull:"):
            HullConfig(**bad)


def test_the_players_hull_lands_on_the_players_in_the_held_out_cameras(panoptic):
    """Carved from the 24 training cameras, seen from the 3 cameras it never used."""
    ds, train = panoptic
    frame = 30
    cams = [c for c in ds.cameras(frame) if c.name in train]
    pts, colors = hull_surface_points(cams, [ds.image(frame, c.name) for c in cams],
                                      [ds.mask(frame, c.name) for c in cams])
    assert len(pts) > 2000
    for cam in [c for c in ds.cameras(frame) if c.name in HELD_OUT]:
        uv, inside = in_view(cam, pts.double().numpy())
        mask = ds.mask(frame, cam.name).numpy()
        x = uv[inside, 0].astype(int)
        y = uv[inside, 1].astype(int)
        assert inside.sum() > 500
        assert mask[y, x].mean() > 0.85, cam.name
        # Coloured like the held-out camera's pixels there (the players and the ball, not the grey dome).
        image = ds.image(frame, cam.name).numpy()
        on = mask[y, x]
        error = np.abs(image[y[on], x[on]] - colors[inside][on].numpy()).mean()
        assert error < 0.12, (cam.name, error)


def test_hull_seeds_fill_the_capacity_on_the_people(panoptic):
    from stgs.train.seeding import initial_points

    ds, names = panoptic
    cams = [c for c in ds.cameras(0) if c.name in names]
    init = initial_points(ds, names, [0, 48], 4096, torch.Generator().manual_seed(0), hull=HullConfig())
    plain = initial_points(ds, names, [0, 48], 4096, torch.Generator().manual_seed(0))
    assert init.triangulated == plain.triangulated < 4096
    assert init.anchored.all() and not plain.anchored[plain.triangulated:].any()  # no filler left
    hull = init.points[init.triangulated:]
    assert np.median(shares_per_point(ds, cams, [0, 48], hull)) > 0.9
    filler = plain.points[plain.triangulated:]
    assert np.median(shares_per_point(ds, cams, [0, 48], filler)) < 0.5
