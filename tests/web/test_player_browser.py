"""The web player in a real headless Chromium (Debian's, SwiftShader's WebGL2) against `stgs serve` on loopback:
playback from the catalogue link, parity with `stgs play` at a scene camera (also on a rung paired with a lossy
keyframe), the decoded features against the
Python decode, seeking, a throttled link, bad manifests, a browser without WebCodecs, a screenshot held to
thresholds, and a plan past its timeout (it fails at once and leaves no browser behind)."""

from __future__ import annotations

import base64
import hashlib
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from stgs.codec.video import AV1, decode_segment
from stgs.metrics import psnr
from stgs.tree import MANIFEST
from tests.web.conftest import ERROR_TEXT, LOADED, WEB_SCENE, browse, need_browser, run_plan

FRAMES = WEB_SCENE.num_gops * WEB_SCENE.gop_size
E = WEB_SCENE.gop_size + 3 - 1  # the feature frames of a GOP (window 3)
SIDE = 4 * WEB_SCENE.grid_side
STATE = ("({current: stgsPlayer.current, ended: stgsPlayer.ended, presented: stgsPlayer.stats.presentedFrames, "
         "dropped: stgsPlayer.stats.dropped, stalls: stgsPlayer.stats.stalls, stallMs: stgsPlayer.stats.stallMs, "
         "decisions: stgsPlayer.stats.decisions, shown: stgsPlayer.stats.shown})")


def player(served: str, scene: str = "small", **params: str) -> str:
    query = "&".join(f"{k}={v}" for k, v in params.items())
    return f"{served}player/?mpd=/{scene}/manifest.mpd" + (f"&{query}" if query else "")


def png(data_url: str) -> np.ndarray:
    raw = np.frombuffer(base64.b64decode(data_url.split(",", 1)[1]), np.uint8)
    return cv2.cvtColor(cv2.imdecode(raw, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(np.float32) / 255


def test_the_demo_scene_plays_to_the_end_from_the_catalogue_link(served):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": served},
        {"click": "a[href*='small']"},
        {"wait": "window.stgsPlayer && stgsPlayer.manifest"},
        {"eval": "stgsPlayer.loop = false"},  # a scene this short loops by default
        {"wait": "window.stgsPlayer && stgsPlayer.ended", "timeout": 180000},
        {"eval": STATE, "as": "state"},
        {"eval": ERROR_TEXT, "as": "error"},
    ]})
    state = out["results"]["state"]
    assert out["results"]["error"] is None and "player/?mpd=" in out["url"]
    assert state["current"] == FRAMES - 1
    # every frame is presented or counted as dropped (SwiftShader renders slower than 12 fps: it drops)
    assert state["presented"] + state["dropped"] == FRAMES
    assert state["stalls"] == 0, f"stalled {state['stallMs']:.0f} ms on loopback"
    assert [d["gop"] for d in state["decisions"]] == list(range(WEB_SCENE.num_gops))
    assert all(d["reason"] for d in state["decisions"])
    assert not [c for c in out["console"] if c["type"] == "error"] and not out["errors"]


@pytest.mark.parametrize("backend", ["weights=texture", "weights=uniform", "deform=webgpu"])
def test_a_frame_at_a_scene_camera_matches_stgs_play(served, tmp_path, backend):
    """Every deformation back end (WebGL2 with its weights in a texture or uniform blocks, WebGPU compute on
    SwiftShader's Vulkan) against the CPU player's frame."""
    gop, frame = 3, 4
    key, value = backend.split("=")
    out = browse({"webgpu": True, "viewport": [360, 300], "steps": [
        {"goto": player(served, camera="cam01", size="96x72", quality="av1q16", autoplay="0", **{key: value})},
        {"wait": LOADED},
        {"eval": f"stgsPlayer.showFrame({gop * WEB_SCENE.gop_size + frame})", "as": "shown"},
        {"eval": "stgsPlayer.capture()", "as": "png"},
    ]})
    assert out["results"]["shown"] == {"gop": gop, "frame": frame}
    web = png(out["results"]["png"])
    start = gop * WEB_SCENE.gop_size / WEB_SCENE.fps
    result = subprocess.run([sys.executable, "-m", "stgs.cli", "play", served + "small/manifest.mpd", "--codec", "av1",
                             "--qp", "16", "--camera", "cam01", "--start", str(start), "--duration",
                             str((frame + 1) / WEB_SCENE.fps), "--out", str(tmp_path / "ref")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    ref = cv2.cvtColor(cv2.imread(str(tmp_path / "ref" / f"{gop * WEB_SCENE.gop_size + frame:05d}.png")),
                       cv2.COLOR_BGR2RGB).astype(np.float32) / 255
    assert web.shape == ref.shape == (72, 96, 3)
    assert ref.std() > 0.05  # a real image, not a flat one that any renderer matches
    assert psnr(torch.from_numpy(web), torch.from_numpy(ref)) >= 40.0


def test_a_rung_paired_with_a_lossy_keyframe_plays_it_as_stgs_play_does(served, web_root, tmp_path):
    """The auto ladder pairs a low rung with the coarse keyframe: the page fetches that keyframe Representation,
    decodes its coarser images and quantised weights, and draws what the CPU player draws."""
    import json

    stats = json.loads((web_root / "paired" / "stats.json").read_text())
    lossy = sorted(rep for rep, info in stats["representations"].items() if info["keyframes"] != "keyframes")
    assert lossy, "the auto ladder paired no rung with the coarse keyframe"
    rep, gop, frame = lossy[0], 3, 4
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, scene="paired", camera="cam01", size="96x72", quality=rep, autoplay="0")},
        {"wait": LOADED},
        {"eval": f"stgsPlayer.showFrame({gop * WEB_SCENE.gop_size + frame})", "as": "shown"},
        {"eval": "stgsPlayer.capture()", "as": "png"},
        {"eval": "performance.getEntriesByType('resource').map(e => e.name)", "as": "fetched"},
    ]})
    assert out["results"]["shown"] == {"gop": gop, "frame": frame}
    fetched = [n for n in out["results"]["fetched"] if n.endswith(".stgk")]
    assert fetched and all("/keyframes-coarse/gop_" in n for n in fetched)
    start = gop * WEB_SCENE.gop_size / WEB_SCENE.fps
    result = subprocess.run([sys.executable, "-m", "stgs.cli", "play", served + "paired/manifest.mpd", "--codec",
                             "av1", "--qp", rep[len("av1q"):], "--camera", "cam01", "--start", str(start),
                             "--duration", str((frame + 1) / WEB_SCENE.fps), "--out", str(tmp_path / "ref"),
                             "--log", str(tmp_path / "log.json")], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert {g["keyframe_rep"] for g in json.loads((tmp_path / "log.json").read_text())["gops"]} == \
        {"keyframes-coarse"}
    ref = cv2.cvtColor(cv2.imread(str(tmp_path / "ref" / f"{gop * WEB_SCENE.gop_size + frame:05d}.png")),
                       cv2.COLOR_BGR2RGB).astype(np.float32) / 255
    web = png(out["results"]["png"])
    assert web.shape == ref.shape == (72, 96, 3) and ref.std() > 0.05
    assert psnr(torch.from_numpy(web), torch.from_numpy(ref)) >= 40.0


def test_the_pages_feature_frames_equal_the_python_decode(served, web_root):
    gop = 2
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, size="64x48", quality="av1q32", autoplay="0", debug="features")},
        {"wait": LOADED},
        {"eval": f"stgsPlayer.showFrame({gop * WEB_SCENE.gop_size + WEB_SCENE.gop_size - 1})", "as": "shown"},
        {"wait": f"[...Array({E}).keys()].every(e => stgsPlayer.digests.has('{gop}:' + e))"},
        {"eval": f"[...Array({E}).keys()].map(e => stgsPlayer.digests.get('{gop}:' + e))", "as": "digests"},
    ]})
    folder = next((web_root / "small").glob("v-*/features/av1q32"))
    frames = decode_segment((folder / "init.mp4").read_bytes(), (folder / f"seg_{gop:05d}.m4s").read_bytes(), E, SIDE,
                            SIDE, codec=AV1)
    assert np.ptp(frames) > 100
    assert out["results"]["digests"] == [hashlib.sha256(f.astype("<u2").tobytes()).hexdigest() for f in frames]


def test_a_seek_lands_on_the_asked_gop_and_fetches_only_from_it(served):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, autoplay="0", size="64x48")},
        {"wait": LOADED},
        {"wait": "stgsPlayer.stats.shown !== null"},
        {"eval": "(performance.clearResourceTimings(), 1)", "as": "_"},
        {"eval": "(() => { const s = document.getElementById('seek'); s.value = '7'; "
                 "s.dispatchEvent(new Event('change')); return 1; })()", "as": "_"},
        {"wait": "stgsPlayer.stats.shown && stgsPlayer.stats.shown.gop === 7"},
        {"eval": "performance.getEntriesByType('resource').map(e => e.name)", "as": "fetched"},
        {"eval": STATE, "as": "state"},
    ]})
    assert out["results"]["state"]["shown"] == {"gop": 7, "frame": 0}
    keyframes = sorted(int(n[-10:-5]) for n in out["results"]["fetched"] if "/keyframes/gop_" in n)
    assert keyframes and keyframes[0] == 7


def test_a_throttled_link_makes_the_abr_go_down_within_a_bounded_stall(served, web_root):
    # A link of (keyframe + lowest rung) / 0.85: the lowest rung fits with room to spare, the top one does not fit
    # in the throughput rule's budget (0.9 x the estimate, less the round trips).
    mpd = (web_root / "small" / "manifest.mpd").read_text()
    keyframe = int(re.search(r'id="keyframes" bandwidth="(\d+)"', mpd)[1])
    ladder = sorted(int(b) for b in re.findall(r'id="av1q\d+" bandwidth="(\d+)"', mpd))
    kbps = (keyframe + ladder[0]) / 0.85 / 1e3
    assert 0.9 * kbps * 1e3 < keyframe + ladder[-1]
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": served + "healthz"},
        {"throttle": {"kbps": kbps, "latencyMs": 40}},
        {"goto": player(served, size="64x48", abr="throughput", loop="0")},
        {"wait": "window.stgsPlayer && stgsPlayer.ended", "timeout": 180000},
        {"eval": STATE, "as": "state"},
    ]})
    state = out["results"]["state"]
    rungs = [d["rung"] for d in state["decisions"]]
    assert "av1q16" not in rungs[1:], rungs  # never the top rung once the throughput is measured
    assert rungs[0] == "av1q41" and len(rungs) == WEB_SCENE.num_gops
    total_s = FRAMES / WEB_SCENE.fps
    assert state["stallMs"] / 1e3 <= 0.5 * total_s, f"stalled {state['stallMs']:.0f} ms of a {total_s:.0f} s scene"


def test_bad_manifests_show_the_error_panel(served):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, scene="broken")},
        {"wait": ERROR_TEXT},
        {"eval": ERROR_TEXT, "as": "broken"},
        {"goto": player(served, scene="foreign")},
        {"wait": ERROR_TEXT},
        {"eval": ERROR_TEXT, "as": "foreign"},
        {"goto": player(served, scene="missing")},
        {"wait": ERROR_TEXT},
        {"eval": ERROR_TEXT, "as": "missing"},
        {"goto": player(served, scene="badquant")},
        {"wait": ERROR_TEXT},
        {"eval": ERROR_TEXT, "as": "badquant"},
    ]})
    r = out["results"]
    assert r["badquant"].startswith("ManifestError: keyframe Representation keyframes-coarse: quant position=17")
    assert r["broken"].startswith("ManifestError: the manifest is not XML")
    assert r["foreign"].startswith("RefusedUrlError: host 192.0.2.7 is neither the manifest's")
    assert r["missing"].startswith("FetchError: manifest:") and "404" in r["missing"]


def test_a_browser_without_webcodecs_says_so(served):
    out = browse({"viewport": [360, 300], "steps": [
        {"initScript": "delete window.VideoDecoder"},
        {"goto": player(served)},
        {"wait": ERROR_TEXT},
        {"eval": ERROR_TEXT, "as": "error"},
    ]})
    assert out["results"]["error"].startswith("UnsupportedError: this browser has no WebCodecs VideoDecoder")


SCREENSHOT_MIN_STD = 0.04
"""A mid-playback frame is a picture, not a flat fill: its pixels' standard deviation is at least this ..."""
SCREENSHOT_MIN_LIT = 0.5
"""... and at least this share of it is not the black background (the static layer fills the view)."""


def test_a_mid_playback_screenshot_holds_its_thresholds(served, tmp_path):
    shot = tmp_path / "web.png"
    browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, camera="cam00")},
        {"wait": LOADED},
        {"wait": f"stgsPlayer.current >= {FRAMES // 2}", "timeout": 120000},
        {"screenshot": str(shot), "selector": "#view"},
    ]})
    image = cv2.imread(str(shot)).astype(np.float32) / 255
    assert image.std() >= SCREENSHOT_MIN_STD
    assert (image.max(axis=2) > 0.05).mean() >= SCREENSHOT_MIN_LIT


def test_the_keyboard_drives_the_player(served, web_root):
    out = browse({"viewport": [360, 300], "steps": [
        {"goto": player(served, autoplay="0", size="64x48")},
        {"wait": LOADED},
        {"wait": "stgsPlayer.stats.shown !== null"},
        {"press": "."},
        {"wait": "stgsPlayer.stats.shown.gop === 1"},
        {"press": "i"},
        {"eval": "document.getElementById('stats').hidden", "as": "stats_hidden"},
        {"press": "2"},
        {"eval": "document.getElementById('camera').value", "as": "camera"},
        {"press": "ArrowLeft"},
        {"eval": "document.getElementById('camera').value", "as": "moved"},
        {"press": " "},
        {"eval": "[stgsPlayer.paused, document.getElementById('play').getAttribute('aria-label')]", "as": "play"},
        {"press": "Tab"},
        {"eval": "document.activeElement.id", "as": "focus"},
        {"eval": "[...document.getElementById('quality').options].map((o) => o.text)", "as": "menu"},
    ]})
    r = out["results"]
    assert r["stats_hidden"] is False and r["camera"] == "1" and r["moved"] == ""
    assert r["play"] == [False, "Pause"]
    assert r["focus"] == "play"  # from the canvas, Tab reaches the controls in order
    # the quality menu names each rung's rendered quality, as the manifest's quality descriptor gives it
    from decimal import ROUND_HALF_UP, Decimal

    from stgs.client.manifest import Presentation

    def js_fixed(value: float, places: str) -> str:  # Number.prototype.toFixed and Math.round: halves go up
        return str(Decimal(value).quantize(Decimal(places), ROUND_HALF_UP))

    pres = Presentation.parse((web_root / "small" / MANIFEST).read_bytes(), "http://x/manifest.mpd", "av1")
    assert [m for m in r["menu"] if m != "auto"] == [
        f"{rung.rep_id} ({js_fixed(rung.bandwidth / 1e3, '1')} kbit/s, {js_fixed(rung.quality.quality, '0.1')} dB)"
        for rung in pres.ladder]


def _browser_processes() -> set[int]:
    pids = set()
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and b"chromium" in (proc / "cmdline").read_bytes():
                pids.add(int(proc.name))
        except OSError:
            pass
    return pids


def test_a_plan_past_its_timeout_fails_and_leaves_no_browser_behind():
    need_browser()
    before = _browser_processes()
    out, failure = run_plan({"viewport": [100, 100], "steps": [
        {"goto": "about:blank"}, {"wait": "false", "timeout": 600000}]}, 8)
    assert out == {} and failure == "the browser plan did not finish in 8 s"
    assert not _browser_processes() - before
