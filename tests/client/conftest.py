"""Shared by the player's tests: one small packed scene (synthesised once per run), the real server on loopback."""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path

import pytest

from stgs.client.fetch.download import DownloadSettings
from stgs.packager import PackConfig, pack
from stgs.server.app import loopback
from stgs.synth import SynthConfig, synthesize

# fps = G: one-second GOPs, so a real-time playback of the 3 GOPs takes 3 s.
SCENE = SynthConfig(grid_side=16, num_gops=3, gop_size=6, fps=6.0, width=64, height=48, num_cameras=2,
                    fit_steps=60)
QUICK = DownloadSettings(retries=1, backoff_s=0.05, read_timeout_s=5.0)


@pytest.fixture(scope="session")
def scene(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("play")
    synthesize(SCENE, base / "model", progress=False)
    pack(base / "model", base / "dash", PackConfig(ladder="fixed",
                                                   qps=(16, 24, 32), av1_qps=(16, 32, 41), jobs=2), progress=False)
    return base


@contextlib.asynccontextmanager
async def serving(root: Path, middleware=None):
    """The real server on a free loopback port; yields the MPD URL."""
    async with loopback(root, (middleware,) if middleware else ()) as base:
        yield base + "manifest.mpd"


def copy_tree(scene: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "dash"
    shutil.copytree(scene / "dash", dst)
    return dst


def segment(root: Path, rel_glob: str) -> Path:
    return next(root.glob(rel_glob))
