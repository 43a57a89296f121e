"""A small layered synth scene (static layer with a degree-1 colour is added by the tests that need one) and random
Gaussians, shared by the interop tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stgs.interop.splats import Splats
from stgs.synth import SynthConfig, synthesize

SCENE = SynthConfig(grid_side=12, num_gops=2, gop_size=6, width=64, height=48, num_cameras=6, fit_steps=60,
                    effects=("rigid", "color", "view_dependent", "static_background"), static_grid_side=10)


@pytest.fixture(scope="session")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("interop") / "scene"
    synthesize(SCENE, out, progress=False)
    return out


def random_splats(n: int, degree: int, seed: int = 0) -> Splats:
    rng = np.random.default_rng(seed)
    f = lambda *shape, loc=0.0, scale=1.0: rng.normal(loc, scale, shape).astype(np.float32)  # noqa: E731
    return Splats(f(n, 3), f(n, 3, loc=-3.0), f(n, 4), f(n), f(n, (degree + 1) ** 2, 3, scale=0.3))
