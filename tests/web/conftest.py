"""Shared by the web player's tests: a small layered scene packed with the browsers' AV1 set, the real `stgs serve`
on loopback (which also serves the built player at /player/), and a driver for Debian's Chromium (web/tools/
browse.mjs, playwright-core on the system binary)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from stgs.cli.browser import WEB
from stgs.cli.browser import browse as run_plan
from stgs.cli.browser import served as serve_root
from stgs.packager import PackConfig, pack
from stgs.synth import SynthConfig, synthesize

DIST = WEB / "dist"
CHROMIUM = shutil.which("chromium")
NODE = shutil.which("node")

WEB_SCENE = SynthConfig(grid_side=16, num_gops=10, gop_size=6, fps=12.0, width=96, height=72, num_cameras=3,
                        fit_steps=60, effects=("rigid", "nonrigid", "color", "static_background"),
                        static_grid_side=16)
"""Ten half-second GOPs of a layered scene (a static layer of 256 Gaussians, a dynamic layer of 256)."""
AV1_QPS = (16, 32, 41)
SMALL_TITLE = "Small <i>scene</i> & co"
"""The `small` scene's title: markup that must show as text."""


def need_node() -> None:
    if NODE is None:
        pytest.skip("Node.js is not installed: the web player is not built")
    if not (DIST / "index.html").is_file():
        pytest.fail("web/dist is missing: ./bin/test builds the web player when Node is installed")


def need_browser() -> None:
    need_node()
    if CHROMIUM is None:
        pytest.skip("Debian's chromium is not installed (./bin/test installs it when root)")


@pytest.fixture(scope="session")
def web_root(tmp_path_factory) -> Path:
    """ROOT with `small` (the scene), `paired` (the same scene on an auto ladder with a lossy keyframe rung),
    `broken` (its manifest not XML), `badquant` (a lossy keyframe's quantisation out of range) and `foreign`
    (segments on another host)."""
    base = tmp_path_factory.mktemp("web")
    synthesize(WEB_SCENE, base / "model", progress=False)
    root = base / "root"
    pack(base / "model", root / "small", PackConfig(ladder="fixed", codecs=("av1",), av1_qps=AV1_QPS, jobs=2,
                                                    title=SMALL_TITLE, description="ten half-second GOPs"),
         progress=False)
    pack(base / "model", root / "paired", PackConfig(codecs=("av1",), av1_qps=AV1_QPS, keyframe_rungs=("coarse",),
                                                     jobs=2), progress=False)
    shutil.copytree(root / "small", root / "broken")
    (root / "broken" / "manifest.mpd").write_text("<MPD this is not xml")
    shutil.copytree(root / "paired", root / "badquant")
    paired = (root / "paired" / "manifest.mpd").read_text()
    badquant = paired.replace('value="position=8;', 'value="position=17;')
    assert badquant != paired
    (root / "badquant" / "manifest.mpd").write_text(badquant)
    shutil.copytree(root / "small", root / "foreign")
    mpd = (root / "small" / "manifest.mpd").read_text()
    foreign = re.sub(r'media="(v-[^"]*/\$RepresentationID\$/gop_)', r'media="http://192.0.2.7/\1', mpd)
    assert foreign != mpd
    (root / "foreign" / "manifest.mpd").write_text(foreign)
    return root


@pytest.fixture(scope="session")
def served(web_root) -> str:
    """The real `stgs serve ROOT` on loopback; yields its base URL (ends in /)."""
    with serve_root(web_root) as base:
        yield base


def browse(plan: dict, timeout: float = 240) -> dict:
    """Run a plan of browser steps (web/tools/browse.mjs) and return what it gathered; a failed step fails."""
    need_browser()
    out, failure = run_plan(plan, timeout)
    assert failure is None, f"{failure} (console: {out.get('console')}, errors: {out.get('errors')})"
    return out


ERROR_TEXT = "document.getElementById('error').hidden ? null : document.getElementById('error').textContent"
"""The error panel's text, or null while it is hidden."""
LOADED = "window.stgsPlayer && stgsPlayer.manifest && document.getElementById('status').textContent === ''"
"""The player has read the manifest and bound its controls."""
