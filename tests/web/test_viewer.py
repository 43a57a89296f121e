"""The viewer for daily use, in Chromium against `stgs serve`: the catalogue's cards (poster, title as text, the
watch link), the poster while the first GOP loads, loop and speed, deep links to a moment and a view (and the
ones that do not hold up), the screenshot, touch, the controls on a phone; a still scene trained from a one-frame
capture; and a GOP trained on the real Panoptic capture, end to end."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from stgs.cli.browser import served as serve_root
from stgs.metrics import psnr
from stgs.packager import PackConfig, pack
from stgs.train import budget, train
from tests.conftest import PANOPTIC, STILL_CAMERA
from tests.web.conftest import ERROR_TEXT, LOADED, SMALL_TITLE, WEB_SCENE, browse, need_browser

FRAMES = WEB_SCENE.num_gops * WEB_SCENE.gop_size
SHOWN = "stgsPlayer.stats.shown !== null"
VIEW = ("({current: stgsPlayer.current, pose: stgsPlayer.camera.pose && stgsPlayer.camera.pose.name, "
        "orbit: stgsPlayer.camera.orbitPose(), loops: stgsPlayer.loops, loop: stgsPlayer.loop, "
        "speed: stgsPlayer.speed})")
WARNINGS = "deep link ignored"
PANOPTIC_GOP = 6
"""Frames of the trained Panoptic GOP."""


def player(served: str, fragment: str = "", **params: str) -> str:
    query = "".join(f"&{k}={v}" for k, v in params.items())
    return f"{served}player/?mpd=/small/manifest.mpd{query}" + (f"#{fragment}" if fragment else "")


def test_the_catalogue_shows_cards_with_posters_and_titles_as_text(served):
    card = "document.querySelector('article[aria-label]')"
    out = browse({"viewport": [800, 600], "steps": [
        {"goto": served},
        {"wait": "[...document.images].every(i => i.complete)"},
        {"eval": "[...document.querySelectorAll('article img')].map(i => [i.naturalWidth, i.naturalHeight])",
         "as": "posters"},
        {"eval": "[...document.querySelectorAll('article h2')].map(h => [h.textContent, h.children.length])",
         "as": "titles"},
        {"eval": f"{card} !== null", "as": "card"},
        {"press": "Tab"},
        {"eval": "document.activeElement.textContent.trim()", "as": "focused"},
        {"click": "a[href*='small']"},
        {"wait": LOADED, "timeout": 60000},
        {"eval": "[document.getElementById('title').textContent, document.title]", "as": "player_title"},
    ]})
    results = out["results"]
    assert [WEB_SCENE.width, WEB_SCENE.height] in results["posters"]  # the first camera's size, decoded
    assert [SMALL_TITLE, 0] in results["titles"]  # the markup is text: no element inside the heading
    assert results["focused"].startswith("watch")  # the first link on the page is a card's watch link
    assert results["player_title"] == [SMALL_TITLE, f"{SMALL_TITLE} · streamstgs"]
    assert "player/?mpd=" in out["url"] and not out["errors"]


def test_the_poster_shows_until_the_first_frame(served):
    poster = "document.getElementById('poster')"
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": served + "healthz"},
        {"throttle": {"kbps": 100, "latencyMs": 40}},  # the first GOP takes seconds, the poster a moment
        {"goto": player(served, size="96x72")},
        {"wait": f"!{poster}.hidden && {poster}.naturalWidth > 0", "timeout": 60000},
        {"eval": f"[{SHOWN}, {poster}.naturalWidth]", "as": "early"},
        {"throttle": None},
        {"wait": f"{SHOWN} && {poster}.hidden", "timeout": 120000},
    ]})
    assert out["results"]["early"] == [False, WEB_SCENE.width]


def test_a_short_scene_loops_and_plays_at_the_speed_asked(served):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, size="64x48", speed="2")},
        {"wait": LOADED},
        {"eval": VIEW, "as": "start"},
        {"wait": "stgsPlayer.loops >= 1 && stgsPlayer.current >= 0 && stgsPlayer.current < 2 * "
                 f"{WEB_SCENE.gop_size}", "timeout": 240000},
        {"eval": VIEW, "as": "looped"},
        {"press": "l"},
        {"eval": VIEW, "as": "toggled"},
    ]})
    r = out["results"]
    assert r["start"]["loop"] is True and r["start"]["speed"] == 2  # 5 s: under ten seconds, it loops
    assert r["looped"]["loops"] >= 1 and 0 <= r["looped"]["current"] < FRAMES  # played past the end
    assert r["toggled"]["loop"] is False
    assert not [c for c in out["console"] if c["type"] == "error"] and not out["errors"]


def test_a_deep_link_lands_on_its_moment_and_camera_and_copy_link_gives_one(served):
    t, cam = 2.3, "cam02"
    frame = round(t * WEB_SCENE.fps)
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, f"t={t}&cam={cam}", size="96x72", autoplay="0")},
        {"wait": f"{LOADED} && {SHOWN}", "timeout": 120000},
        {"eval": VIEW, "as": "landed"},
        {"wait": "document.getElementById('camera').selectedOptions[0].textContent === 'cam02'"},  # the menu too
        {"eval": "stgsPlayer.camera.orbit(0.3, 0.1), stgsPlayer.invalidate(), true"},
        {"click": "#link"},
        {"wait": "document.getElementById('status').textContent !== ''"},
        {"eval": "[location.hash, document.getElementById('status').textContent]", "as": "link"},
        {"eval": "stgsPlayer.camera.orbitPose()", "as": "orbit"},
    ]})
    landed = out["results"]["landed"]
    assert landed["current"] == frame and landed["pose"] == cam
    fragment, status = out["results"]["link"]
    assert fragment.startswith(f"#t={frame / WEB_SCENE.fps:.3f}&cam=") and status
    again = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, fragment[1:], size="96x72", autoplay="0")},
        {"wait": f"{LOADED} && {SHOWN}", "timeout": 120000},
        {"eval": VIEW, "as": "landed"},
    ]})
    landed = again["results"]["landed"]
    assert landed["current"] == frame and landed["pose"] is None
    assert landed["orbit"] == out["results"]["orbit"]  # the pose round-trips through the link
    assert not [c for c in again["console"] if WARNINGS in c["text"]]


@pytest.mark.parametrize("fragment, warned", [
    ("t=NaN&cam=nope", ["t=NaN", "cam=nope"]),
    ("t=1e308", ["t=1e308"]),
    ("t=-1&cam=1,2,3", ["t=-1", "cam=1,2,3"]),
    ("cam=0,0,0,0,0,1e9,60", ["cam=0,0,0,0,0,1e9,60"]),
])
def test_a_fragment_that_does_not_hold_up_is_ignored_with_a_warning(served, fragment, warned):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, fragment, size="64x48", autoplay="0")},
        {"wait": f"{LOADED} && {SHOWN}", "timeout": 120000},
        {"eval": VIEW, "as": "view"},
    ]})
    view = out["results"]["view"]
    assert view["current"] == 0 and view["pose"] == "cam00"  # the default view: the first frame, the first camera
    warnings = [c["text"] for c in out["console"] if c["type"] == "warning" and WARNINGS in c["text"]]
    assert len(warnings) == len(warned) and all(any(w in text for text in warnings) for w in warned), warnings
    assert not out["errors"] and not [c for c in out["console"] if c["type"] == "error"]


def test_the_screenshot_is_a_png_of_the_canvas(served, tmp_path):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, "t=1&cam=cam01", size="96x72", autoplay="0")},
        {"wait": f"{LOADED} && {SHOWN}", "timeout": 120000},
        {"download": "#screenshot", "path": str(tmp_path / "shot.png"), "as": "name"},
        {"eval": "[document.getElementById('view').width, document.getElementById('view').height]", "as": "size"},
    ]})
    data = (tmp_path / "shot.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imread(str(tmp_path / "shot.png"))
    assert [image.shape[1], image.shape[0]] == out["results"]["size"] == [96, 72] and image.std() > 5
    assert out["results"]["name"].endswith("-t1.00s.png") and out["results"]["name"].startswith("Small_")


def test_touch_orbits_with_one_finger_and_zooms_with_a_pinch(served):
    camera = "[stgsPlayer.camera.yaw, stgsPlayer.camera.pitch, stgsPlayer.camera.radius, stgsPlayer.camera.pose]"
    out = browse({"viewport": [800, 600], "touch": True, "steps": [
        {"goto": player(served, size="96x72", autoplay="0")},
        {"wait": f"{LOADED} && {SHOWN}", "timeout": 120000},
        {"eval": "document.elementFromPoint(300, 150).id", "as": "under"},
        {"eval": camera, "as": "before"},
        {"touch": [[300, 150]], "to": [[380, 130]]},
        {"eval": camera, "as": "orbited"},
        {"touch": [[350, 150], [410, 150]], "to": [[310, 150], [450, 150]]},  # fingers apart: closer
        {"eval": camera, "as": "pinched"},
    ]})
    r = out["results"]
    assert r["under"] == "view"
    (yaw0, pitch0, radius0, pose0), (yaw1, pitch1, radius1, pose1) = r["before"], r["orbited"]
    assert pose0 is not None and pose1 is None  # the snapped scene camera is left for the orbit
    assert yaw1 == pytest.approx(yaw0 - 80 * 0.005) and pitch1 == pytest.approx(pitch0 - 20 * 0.005)
    assert radius1 == pytest.approx(radius0)
    yaw2, _, radius2, _ = r["pinched"]
    assert yaw2 == pytest.approx(yaw1) and radius2 < 0.6 * radius1  # from 60 px apart to 140 px apart
    assert not out["errors"]


@pytest.fixture(scope="module")
def panoptic_tree(tmp_path_factory) -> Path:
    """One GOP of the Panoptic capture trained on the quick layered budget at quarter size, packed with one AV1 rung
    (skipped without ../shared)."""
    if not PANOPTIC.is_dir():
        pytest.skip("../shared/data/panoptic-basketball is absent")
    need_browser()
    base = tmp_path_factory.mktemp("panoptic")
    train(PANOPTIC, base / "model", budget("quick", layers="layered", gop_size=PANOPTIC_GOP, max_gops=1, scale=0.25),
          progress=False)
    pack(base / "model", base / "root" / "basketball", PackConfig(ladder="fixed", codecs=("av1",), av1_qps=(16,),
                                                                  jobs=2, title="Panoptic basketball"), progress=False)
    return base / "root" / "basketball"


def test_a_trained_panoptic_gop_plays_and_matches_stgs_play_at_a_scene_camera(panoptic_tree, tmp_path):
    """A real capture end to end in Chromium: played to its end with no error, then its frame at a scene camera
    against `stgs play --camera`, then driven by touch (one finger orbits, a pinch zooms, and the view redraws)."""
    cameras = json.loads((panoptic_tree / "cameras.json").read_text())["cameras"]
    cam = next(c for c in cameras if c["name"] == "14")  # a held-out camera: the model never saw it
    size, frame = f"{cam['width']}x{cam['height']}", PANOPTIC_GOP // 2
    pose = "[stgsPlayer.camera.yaw, stgsPlayer.camera.radius, stgsPlayer.stats.frameTimes.length]"  # draws so far
    with serve_root(panoptic_tree.parent) as base:
        url = f"{base}player/?mpd=/basketball/manifest.mpd&size={size}&camera={cam['name']}&loop=0"
        out = browse({"viewport": [800, 600], "touch": True, "steps": [
            {"goto": url},
            {"wait": "window.stgsPlayer && stgsPlayer.ended", "timeout": 180000},
            {"eval": "stgsPlayer.current", "as": "last"},
            {"eval": f"stgsPlayer.showFrame({frame})", "as": "shown"},
            {"eval": "stgsPlayer.capture()", "as": "png"},
            {"eval": f"(window.before = {pose})", "as": "before"},
            {"touch": [[300, 150]], "to": [[380, 150]]},
            {"touch": [[350, 150], [410, 150]], "to": [[310, 150], [450, 150]]},
            {"wait": "stgsPlayer.stats.frameTimes.length > window.before[2]", "timeout": 30000},
            {"eval": pose, "as": "after"},
        ]})
        result = subprocess.run([sys.executable, "-m", "stgs.cli", "play", base + "basketball/manifest.mpd",
                                 "--codec", "av1", "--qp", "16", "--camera", cam["name"], "--duration",
                                 str((frame + 1) / 30.0), "--out", str(tmp_path / "ref")],
                                capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    r = out["results"]
    assert r["last"] == PANOPTIC_GOP - 1 and r["shown"] == {"gop": 0, "frame": frame}
    assert not out["errors"] and not [c for c in out["console"] if c["type"] == "error"]
    ref = cv2.cvtColor(cv2.imread(str(tmp_path / "ref" / f"{frame:05d}.png")), cv2.COLOR_BGR2RGB) / 255.0
    raw = np.frombuffer(base64.b64decode(r["png"].split(",", 1)[1]), np.uint8)
    web = cv2.cvtColor(cv2.imdecode(raw, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) / 255.0
    assert web.shape == ref.shape == (cam["height"], cam["width"], 3) and ref.std() > 0.05
    assert psnr(torch.from_numpy(web), torch.from_numpy(ref)) >= 40.0
    (yaw0, radius0, _), (yaw1, radius1, _) = r["before"], r["after"]
    assert yaw1 == pytest.approx(yaw0 - 80 * 0.005) and radius1 < 0.6 * radius0


def test_a_still_scene_shows_in_the_catalogue_and_the_player_and_matches_stgs_play(still_scene, tmp_path):
    """A one-frame capture trained and packed as a still (tests.conftest.still_scene): its card says so, the player
    draws it with the camera's controls alone (no clock), redraws it when the view moves, links to a view with no
    time, and its frame at a scene camera is `stgs play --camera`'s."""
    hidden = ("['play', 'seek', 'loop', 'speed', 'quality']"
              ".map(id => document.getElementById(id).closest('[hidden]') !== null)")
    draws = "stgsPlayer.stats.frameTimes.length"
    root = tmp_path / "root"
    shutil.copytree(still_scene / "tree" / "still", root / "still")
    shutil.copytree(root / "still", root / "badstill")  # a feature set beside the static layer, and no keyframe set
    mpd = (root / "still" / "manifest.mpd").read_text()
    bad = mpd.replace("</Period>", '<AdaptationSet id="3" contentType="video" mimeType="video/mp4">'
                      '<SupplementalProperty schemeIdUri="urn:streamstgs:features:2026" value="tiles=4x4;'
                      'channels=16;bits=10"/></AdaptationSet></Period>')
    assert bad != mpd
    (root / "badstill" / "manifest.mpd").write_text(bad)
    with serve_root(root) as base:
        url = f"{base}player/?mpd=/still/manifest.mpd&size=96x72&camera={STILL_CAMERA}"
        out = browse({"viewport": [640, 480], "steps": [
            {"goto": base},
            {"eval": "document.querySelector('article .meta').textContent", "as": "meta"},
            {"click": "a[href*='still']"},
            {"wait": f"{LOADED} && {SHOWN}", "timeout": 60000},
            {"eval": f"[stgsPlayer.still, {hidden}, document.getElementById('time').textContent]", "as": "page"},
            {"goto": url},
            {"wait": f"{LOADED} && {SHOWN}", "timeout": 60000},
            {"eval": "stgsPlayer.capture()", "as": "png"},
            {"eval": f"(window.before = {draws})", "as": "before"},
            {"press": "ArrowLeft"},
            {"wait": f"{draws} > window.before", "timeout": 30000},
            {"click": "#link"},
            {"eval": "location.hash", "as": "link"},
            {"goto": url + "#t=2&cam=cam01"},  # the same page: its fragment changes
            {"wait": "stgsPlayer.camera.pose && stgsPlayer.camera.pose.name === 'cam01'", "timeout": 30000},
            {"wait": f"{draws} > window.before + 1", "timeout": 30000},
            {"goto": f"{base}player/?mpd=/badstill/manifest.mpd"},
            {"wait": ERROR_TEXT},
            {"eval": ERROR_TEXT, "as": "bad"},
            {"initScript": "delete window.VideoDecoder"},  # a still needs no video decoder
            {"goto": url},
            {"wait": f"{LOADED} && {SHOWN}", "timeout": 60000},
            {"eval": "typeof VideoDecoder", "as": "decoder"},
        ]})
        result = subprocess.run([sys.executable, "-m", "stgs.cli", "play", base + "still/manifest.mpd", "--camera",
                                 STILL_CAMERA, "--out", str(tmp_path / "ref")], capture_output=True, text=True,
                                timeout=300)
    assert result.returncode == 0, result.stderr
    r = out["results"]
    assert r["meta"] == f"still · {24 ** 2} Gaussians"
    assert r["page"] == [True, [True] * 5, "still"] and r["decoder"] == "undefined"
    assert r["bad"] == "ManifestError: a still scene (no keyframe AdaptationSet) has no feature set either"
    assert "t=" not in r["link"] and "cam=" in r["link"]
    warnings = [c["text"] for c in out["console"] if WARNINGS in c["text"]]
    assert len(warnings) == 1 and "no timeline" in warnings[0]
    assert not out["errors"] and [c["text"] for c in out["console"] if c["type"] == "error"] == [r["bad"]]
    ref = cv2.cvtColor(cv2.imread(str(tmp_path / "ref" / "00000.png")), cv2.COLOR_BGR2RGB) / 255.0
    raw = np.frombuffer(base64.b64decode(r["png"].split(",", 1)[1]), np.uint8)
    web = cv2.cvtColor(cv2.imdecode(raw, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) / 255.0
    assert web.shape == ref.shape == (72, 96, 3) and ref.std() > 0.05
    assert psnr(torch.from_numpy(web), torch.from_numpy(ref)) >= 40.0


def test_on_a_phone_the_controls_are_one_row_that_scrolls_to_a_focused_control(served):
    rect = ("(id => { const r = document.getElementById(id).getBoundingClientRect(); "
            "return [r.left, r.right, r.height]; })")
    out = browse({"viewport": [360, 640], "touch": True, "steps": [
        {"goto": player(served, size="64x48")},
        {"wait": LOADED, "timeout": 60000},
        {"eval": "(c => [c.scrollWidth, c.clientWidth])(document.getElementById('controls'))", "as": "widths"},
        {"eval": "(document.getElementById('fullscreen').focus(), 1)", "as": "_"},
        {"eval": f"[{rect}('controls'), {rect}('play'), {rect}('fullscreen')]", "as": "rects"},
    ]})
    (scroll, width), (controls, play, last) = out["results"]["widths"], out["results"]["rects"]
    assert scroll > width == 360  # more controls than fit: they scroll sideways ...
    assert controls[2] < 2 * play[2]  # ... in one row, not three over the picture
    assert controls[0] <= last[0] and last[1] <= controls[1]  # the last control, focused, is in view
