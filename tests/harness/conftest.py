"""The harness tests' packaged scene: small enough to simulate and emulate in seconds, shared by the modules."""

from __future__ import annotations

from pathlib import Path

import pytest

from stgs.packager import PackConfig, pack
from stgs.synth import SynthConfig, synthesize

# fps = G: one-second GOPs
SCENE = SynthConfig(grid_side=16, num_gops=3, gop_size=6, fps=6.0, width=48, height=36, num_cameras=2,
                    fit_steps=40)


@pytest.fixture(scope="session")
def packed(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("harness")
    synthesize(SCENE, base / "model", progress=False)
    pack(base / "model", base / "dash", PackConfig(ladder="fixed",
                                                   qps=(16, 24, 32), codecs=("hevc",), jobs=2), progress=False)
    return base / "dash"
