"""The Panoptic capture for the training tests that need real data, and where points land in its masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from stgs.data import open_dataset, split
from stgs.synth import SynthConfig, synthesize
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.train.triangulate import in_view
from tests.conftest import PANOPTIC

HELD_OUT = ["1", "14", "27"]

SCENE = SynthConfig(grid_side=16, num_gops=1, gop_size=6, width=96, height=72, num_cameras=8, fit_steps=30,
                    effects=(*DEFAULT_EFFECTS, "static_background"), static_grid_side=16)
"""A small synthetic scene with a static background (layered training's tests)."""
LAYERED = {"gop_size": 6, "max_gops": 1, "layers": "layered", "grid_side": 12, "static_grid_side": 16}
"""Training overrides of the quick budget for SCENE."""


@pytest.fixture(scope="session")
def layered_scene(tmp_path_factory) -> Path:
    """SCENE, synthesised once."""
    out = tmp_path_factory.mktemp("layered") / "scene"
    synthesize(SCENE, out, progress=False)
    return out


@pytest.fixture(scope="session")
def panoptic():
    """The Panoptic dataset and its training camera names (HELD_OUT held out)."""
    if not PANOPTIC.is_dir():
        pytest.skip("../shared/data/panoptic-basketball is absent")
    ds = open_dataset(PANOPTIC)
    return ds, split(ds, HELD_OUT)[0]


@pytest.fixture(scope="module")
def panoptic_frame0(panoptic):
    """The Panoptic dataset and its training cameras at frame 0."""
    ds, names = panoptic
    return ds, [c for c in ds.cameras(0) if c.name in names]


def mask_hits(ds, cams, frames: list[int], pts: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(C, P) bool each: whether camera c sees point p, and whether it sees it on a masked pixel at any of
    `frames`."""
    xyz = pts.double().numpy()
    seen, hits = np.zeros((len(cams), len(xyz)), bool), np.zeros((len(cams), len(xyz)), bool)
    for c, cam in enumerate(cams):
        uv, inside = in_view(cam, xyz)
        x = np.clip(uv[:, 0].astype(int), 0, cam.width - 1)
        y = np.clip(uv[:, 1].astype(int), 0, cam.height - 1)
        for f in frames:
            hits[c] |= ds.mask(f, cam.name).numpy()[y, x]
        seen[c], hits[c] = inside, hits[c] & inside
    return seen, hits


def shares_per_point(ds, cams, frames: list[int], pts: torch.Tensor) -> np.ndarray:
    """(P,) per point, the share of the cameras that see it that see it on a masked pixel at any of `frames`."""
    seen, hits = mask_hits(ds, cams, frames, pts)
    return hits.sum(0) / np.maximum(seen.sum(0), 1)
