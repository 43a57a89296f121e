"""`stgs play` against the real server on loopback: fidelity, ladder, prefetch, stalls, bad input."""

from __future__ import annotations

import asyncio
import json
import math
import struct
import sys

import cv2
import pytest
import torch
from aiohttp import web

from stgs.camera import Camera
from stgs.client import PlaybackError, PlayConfig, play
from stgs.client.config import ViewSpec
from stgs.errors import StgsError
from stgs.metrics import psnr
from stgs.model.renderer import FrameRenderer
from stgs.model.store import load_model
from stgs.synth import load_ground_truth
from tests.client.conftest import QUICK, SCENE, copy_tree, segment, serving


async def test_streamed_frames_at_qp16_match_the_uncompressed_model(scene, tmp_path):
    frames_dir = tmp_path / "frames"
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=16, view=ViewSpec(camera="cam00"), out=frames_dir,
                                    log=tmp_path / "log.json", download=QUICK))
    assert [g["qp"] for g in log["gops"]] == [16, 16, 16] and log["error"] is None
    assert json.loads((tmp_path / "log.json").read_text()) == log
    _, gops = load_model(scene / "model")
    cam = next(c for c in load_ground_truth(scene / "model")[1] if c.name == "cam00")
    pngs = sorted(frames_dir.glob("*.png"))
    assert len(pngs) == SCENE.num_gops * SCENE.gop_size
    values = []
    for png in pngs:
        f = int(png.stem)
        local = FrameRenderer(gops[f // SCENE.gop_size]).render(f % SCENE.gop_size, cam).clamp(0, 1)
        streamed = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
        values.append(psnr(torch.from_numpy(streamed).float() / 255, local))
    assert min(values) >= 40.0, values


async def test_pinned_qps_give_decreasing_bytes(scene):
    sizes = []
    async with serving(scene / "dash") as url:
        for qp in (16, 24, 32):
            log = await play(PlayConfig(url, qp=qp, download=QUICK, view=ViewSpec(width=32, height=24)))
            assert {g["qp"] for g in log["gops"]} == {qp}
            sizes.append(sum(g["feature_bytes"] for g in log["gops"]))
    assert sizes[0] > sizes[1] > sizes[2]


async def test_prefetch_means_no_wait_at_gop_boundaries(scene):
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, abr="dynamic", realtime=True, download=QUICK,
                                    view=ViewSpec(width=32, height=24)))
    assert log["gops_played"] == 3 and log["stalls"] == {"count": 0, "total_s": 0.0}
    assert [g["boundary_wait_s"] for g in log["gops"][1:]] == [0.0, 0.0]
    assert log["dropped_frames"] == 0 and log["rendered_frames"] == 18
    for g in log["gops"]:
        assert g["decode_s"] > 0 and g["download_s"] > 0 and len(g["render_ms"]) == SCENE.gop_size


async def test_a_throttled_server_causes_counted_stalls(scene):
    @web.middleware
    async def slow_media(request, handler):  # test-only delay: every media segment after GOP 0
        if request.path.endswith(".m4s") and not request.path.endswith("seg_00000.m4s"):
            await asyncio.sleep(1.6)
        return await handler(request)

    async with serving(scene / "dash", slow_media) as url:
        log = await play(PlayConfig(url, qp=32, realtime=True, download=QUICK, view=ViewSpec(width=32, height=24)))
    assert log["error"] is None and log["gops_played"] == 3
    assert log["stalls"]["count"] >= 1 and log["stalls"]["total_s"] > 0.3
    assert log["stalls"]["total_s"] == pytest.approx(sum(g["stall_s"] for g in log["gops"]))


async def test_start_time_and_duration_pick_the_gops(scene, tmp_path):
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=24, start_s=1.5, duration_s=1.0, download=QUICK,
                                    out=tmp_path / "clip.mp4", view=ViewSpec(width=32, height=24)))
    assert [g["index"] for g in log["gops"]] == [1] and log["frames"] == SCENE.gop_size
    cap = cv2.VideoCapture(str(tmp_path / "clip.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == SCENE.gop_size
    assert not list(tmp_path.glob(".clip.mp4*"))  # no temp file left


async def test_a_missing_segment_falls_back_to_the_lowest_rung(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    segment(root, "v-*/features/qp16/seg_00001.m4s").unlink()
    async with serving(root) as url:
        log = await play(PlayConfig(url, qp=16, download=QUICK, view=ViewSpec(width=32, height=24)))
    assert [g["qp"] for g in log["gops"]] == [16, 32, 16]
    assert any("fallback from qp16" in e and "404" in e for e in log["gops"][1]["events"])
    async with serving(root) as url:
        (segment(root, "v-*/features/qp32/seg_00002.m4s")).unlink()
        with pytest.raises(PlaybackError, match=r"GOP 2: .*HTTP 404"):
            await play(PlayConfig(url, qp=32, download=QUICK, view=ViewSpec(width=32, height=24)))


async def test_a_corrupt_feature_segment_falls_back_and_is_logged(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    seg = segment(root, "v-*/features/qp24/seg_00001.m4s")
    seg.write_bytes(seg.read_bytes()[:200])  # truncated: decodes to too few frames
    async with serving(root) as url:
        log = await play(PlayConfig(url, qp=24, download=QUICK, view=ViewSpec(width=32, height=24)))
    assert [g["qp"] for g in log["gops"]] == [24, 32, 24]
    assert any("does not decode" in e for e in log["gops"][1]["events"])


async def test_a_garbage_keyframe_is_refetched_then_refused(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    kf = segment(root, "v-*/keyframes/gop_00001.stgk")
    kf.write_bytes(b"\x00" * kf.stat().st_size)
    with pytest.raises(PlaybackError, match="keyframe segment of GOP 1"):
        async with serving(root) as url:
            await play(PlayConfig(url, qp=32, download=QUICK, view=ViewSpec(width=32, height=24),
                                  log=tmp_path / "log.json"))
    log = json.loads((tmp_path / "log.json").read_text())
    assert "keyframe segment of GOP 1" in log["error"] and log["gops_played"] == 1


async def test_a_keyframe_claiming_a_huge_gaussian_count_is_refused(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    kf = segment(root, "v-*/keyframes/gop_00000.stgk")
    data = kf.read_bytes()
    size = struct.unpack_from("<Q", data)[0]
    header = data[8:8 + size].replace(b'\\"capacity\\": \\"256\\"', b'\\"capacity\\": \\"999999999\\"')
    assert header != data[8:8 + size]
    kf.write_bytes(struct.pack("<Q", len(header)) + header + data[8 + size:])
    with pytest.raises(PlaybackError, match="capacity is '999999999', expected '256'"):
        async with serving(root) as url:
            await play(PlayConfig(url, download=QUICK, view=ViewSpec(width=32, height=24)))


async def test_an_oversized_segment_is_refused_before_it_is_read(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    seg = segment(root, "v-*/features/qp32/seg_00000.m4s")
    seg.write_bytes(seg.read_bytes() + b"\x00" * (4 << 20))  # far over qp32's @bandwidth x duration
    with pytest.raises(PlaybackError, match=r"over the .*-byte limit"):
        async with serving(root) as url:
            await play(PlayConfig(url, qp=32, download=QUICK, view=ViewSpec(width=32, height=24)))


async def test_another_profile_is_refused(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    mpd = root / "manifest.mpd"
    mpd.write_bytes(mpd.read_bytes().replace(b",urn:streamstgs:profile:2026", b""))
    with pytest.raises(PlaybackError, match="not a StreamSTGS manifest"):
        async with serving(root) as url:
            await play(PlayConfig(url, download=QUICK))


async def test_server_gone_mid_stream_is_an_error_not_a_hang(scene, tmp_path):
    async with serving(scene / "dash") as url:
        task = asyncio.create_task(play(PlayConfig(url, qp=32, realtime=True, buffer_s=1.0, download=QUICK,
                                                   view=ViewSpec(width=32, height=24),
                                                   log=tmp_path / "log.json")))
        await asyncio.sleep(0.6)  # GOP 0 is playing, GOP 1 is not fetched yet (one-GOP buffer)
    with pytest.raises(PlaybackError, match=r"GOP [12]"):
        await asyncio.wait_for(task, timeout=30)
    log = json.loads((tmp_path / "log.json").read_text())
    assert log["error"] and log["retries"] >= 1


async def test_scene_camera_and_explicit_pose(scene, tmp_path):
    async with serving(scene / "dash") as url:
        with pytest.raises(StgsError, match="no camera 'nope'"):
            await play(PlayConfig(url, view=ViewSpec(camera="nope"), download=QUICK))
        await play(PlayConfig(url, duration_s=0.5, view=ViewSpec(eye=(0, 1, 3), target=(0, 0.5, 0), width=40,
                                                                 height=30), out=tmp_path / "pose"))
    first = cv2.imread(str(sorted((tmp_path / "pose").glob("*.png"))[0]))
    assert first.shape == (30, 40, 3) and first.std() > 3


async def test_the_default_orbit_circles_inside_a_surrounding_rig(scene, tmp_path):
    """With cameras.json describing a rig around the scene (a capture dome), the default orbit is the rig
    orbit, rendered exactly as a local render from its first camera."""
    from stgs.camera import intrinsics, look_at, rig_orbit
    from stgs.tree import CAMERAS, CAMERAS_FORMAT

    root = copy_tree(scene, tmp_path)
    rig = [Camera(f"r{i}", intrinsics(64, 48, 50.0),
                  look_at((3 * math.cos(a), 1.5, 3 * math.sin(a)), (0.0, 0.0, 0.0)), 64, 48)
           for i, a in enumerate(2 * math.pi * k / 5 for k in range(5))]
    doc = {"format": CAMERAS_FORMAT, "version": 1, "cameras": [c.to_json() for c in rig]}
    (root / CAMERAS).write_text(json.dumps(doc))
    async with serving(root) as url:
        await play(PlayConfig(url, qp=16, duration_s=0.5, view=ViewSpec(width=40, height=30),
                              out=tmp_path / "orbit", download=QUICK))
    first = cv2.cvtColor(cv2.imread(str(sorted((tmp_path / "orbit").glob("*.png"))[0])), cv2.COLOR_BGR2RGB)
    _, gops = load_model(scene / "model")
    expected = FrameRenderer(gops[0]).render(0, rig_orbit(rig, 3, 40, 30)[0]).clamp(0, 1)
    assert first.std() > 3
    assert psnr(torch.from_numpy(first).float() / 255, expected) >= 40.0


async def _stgs(*args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "stgs.cli", *args,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), timeout=120)
    return proc.returncode, out.decode(), err.decode()


async def test_the_play_command(scene, tmp_path):
    path = tmp_path / "path.json"
    cams = load_ground_truth(scene / "model")[1]
    path.write_text(json.dumps([Camera.to_json(c) for c in cams]))
    async with serving(scene / "dash") as url:
        code, out, err = await _stgs("play", url, "--path", str(path), "--out", str(tmp_path / "o.mp4"))
        assert code == 0, err
        assert "played 3 GOP(s), 18 frames" in out and "stalls 0" in out
        assert json.loads((tmp_path / "playback.json").read_text())["frames"] == 18
        for args, message in [((url.replace("manifest", "missing"),), "cannot fetch the manifest"),
                              ((url, "--qp", "17"), "--qp 17 is not offered: the scene has QPs 32, 24, 16"),
                              (("ftp://x/m.mpd",), "must start with http"),
                              ((url, "--camera", "cam99"), "no camera 'cam99'"),
                              ((url, "--path", str(tmp_path / "nope.json")), "cannot read the camera path")]:
            code, out, err = await _stgs("play", *args)
            lines = err.strip().splitlines()
            assert code == 2 and len(lines) == 1 and lines[0].startswith("stgs: ") and message in lines[0], err
        code, out, err = await _stgs("play", url, "--render-ahead", "-1")  # argparse's usage, then the error
        assert code == 2 and "argument --render-ahead: must be 0 or more: -1" in err.strip().splitlines()[-1]
