"""The Python player on the AV1 feature set (the browsers' codec): it plays `--codec av1` end to end, matches
the HEVC playback closely, refuses an AV1 segment of another GOP, of another size or bit depth, or truncated,
falling back as it does for HEVC, and a tree packed with AV1 alone plays in `stgs play` and in the simulator."""

from __future__ import annotations

import io
import json

import av
import numpy as np
import pytest
from aiohttp import web

from stgs.client import PlaybackError, PlayConfig, play
from stgs.client.config import ViewSpec
from stgs.client.manifest import Presentation
from stgs.codec.mp4 import set_timeline, split_fragmented
from stgs.codec.video import VideoTiming
from stgs.errors import MPDError
from stgs.harness.ladder import load_ladder
from stgs.harness.scenario import scenario_from_dict
from stgs.harness.sim import simulate
from stgs.metrics import psnr
from stgs.packager import MANIFEST, PackConfig, pack
from tests.client.conftest import QUICK, SCENE, copy_tree, segment, serving
from tests.client.test_hostile_server import HostileServer, hostile, play_bounded
from tests.conftest import run_stgs as stgs

VIEW = ViewSpec(width=32, height=24)


async def frames_of(url: str, codec: str, qp: int, camera) -> tuple[dict, list]:
    """The playback log and every frame the player drew, rendered again at `camera` (the frame hook)."""
    frames = []

    def hook(k, i, renderer, window):
        frames.append(renderer.render(i, camera, window=window))

    log = await play(PlayConfig(url, codec=codec, qp=qp, download=QUICK, view=VIEW), on_frame=hook)
    return log, frames


async def test_the_av1_set_plays_end_to_end_and_looks_like_the_hevc_one(scene):
    from stgs.synth import load_ground_truth

    camera = load_ground_truth(scene / "model")[1][0]
    async with serving(scene / "dash") as url:
        av1_log, av1_frames = await frames_of(url, "av1", 16, camera)
        hevc_log, hevc_frames = await frames_of(url, "auto", 16, camera)
    assert av1_log["codec"] == "av1" and hevc_log["codec"] == "hevc" and av1_log["error"] is None
    assert [g["rep"] for g in av1_log["gops"]] == ["av1q16"] * SCENE.num_gops
    assert [g["rep"] for g in hevc_log["gops"]] == ["qp16"] * SCENE.num_gops
    assert len(av1_frames) == len(hevc_frames) == SCENE.num_gops * SCENE.gop_size
    worst = min(psnr(a, h) for a, h in zip(av1_frames, hevc_frames, strict=True))
    assert worst > 35.0  # two codecs of the same features: close, not identical


async def test_adaptive_play_stays_on_the_chosen_set(scene):
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, codec="av1", abr="dynamic", download=QUICK, view=VIEW))
    assert {g["rep"][:4] for g in log["gops"]} == {"av1q"}


def test_a_codec_the_tree_lacks_is_a_clear_error(scene, tmp_path):
    alone = tmp_path / "hevc"
    pack(scene / "model", alone, PackConfig(ladder="fixed", qps=(24,), codecs=("hevc",), jobs=2), progress=False)
    with pytest.raises(MPDError, match="no av1 feature set \\(it offers hevc\\)"):
        Presentation.parse((alone / MANIFEST).read_bytes(), "http://h/manifest.mpd", "av1")
    pres = Presentation.parse((alone / MANIFEST).read_bytes(), "http://h/manifest.mpd", "auto")
    assert pres.feature_codec.name == "hevc"


def test_a_descriptor_whose_depth_is_not_the_codecs_is_refused(scene):
    data = (scene / "dash" / MANIFEST).read_bytes().replace(b"bits=10", b"bits=12")
    with pytest.raises(MPDError, match="av1 carries 10-bit codes, its descriptor says bits=12"):
        Presentation.parse(data, "http://h/manifest.mpd", "av1")


async def test_an_av1_segment_of_another_gop_is_refused(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))

    async def gop0(request: web.Request, path) -> web.StreamResponse:
        return web.Response(body=path.with_name("seg_00000.m4s").read_bytes())

    server.on(r"features/av1q\d+/seg_00001", gop0)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match=r"GOP 1: .*starts at 0\.000 s, expected 1\.000 s"):
            await play_bounded(base + "manifest.mpd", tmp_path, codec="av1", qp=16)


def foreign_av1(frames: int, side: int, pix_fmt: str) -> tuple[bytes, bytes]:
    """(init, media) of an AV1 stream not made by the packager: another size or bit depth."""
    out = io.BytesIO()
    options = {"movflags": "+frag_keyframe+empty_moov+default_base_moof", "frag_duration": "2000000000"}
    with av.open(out, "w", format="mp4", options=options) as c:
        stream = c.add_stream("libsvtav1", rate=frames, options={"preset": "12"})
        stream.width = stream.height = side
        stream.pix_fmt = pix_fmt
        for i in range(frames):
            frame = av.VideoFrame(side, side, pix_fmt)
            for plane in frame.planes:
                dtype = np.uint16 if pix_fmt.endswith("10le") else np.uint8
                np.frombuffer(plane, dtype)[:] = 100
            frame.pts = i
            c.mux(stream.encode(frame))
        c.mux(stream.encode(None))
    return split_fragmented(out.getvalue())


@pytest.mark.parametrize("case, side, pix_fmt, event", [
    ("truncated", None, None, "does not decode"),
    ("size", 32, "yuv420p10le", "is 32x32 yuv420p10le, expected 64x64"),
    ("bit depth", 64, "yuv420p", "is 64x64 yuv420p, expected 64x64 yuv420p10le (10-bit av1)"),
])
async def test_a_bad_av1_segment_falls_back_to_the_lowest_rung(scene, tmp_path, case, side, pix_fmt, event):
    root = copy_tree(scene, tmp_path)
    seg = segment(root, "v-*/features/av1q16/seg_00001.m4s")
    if side is None:
        seg.write_bytes(seg.read_bytes()[:200])
    else:
        _, media = foreign_av1(SCENE.gop_size + 2, side, pix_fmt)
        e = SCENE.gop_size + 2
        ticks = VideoTiming.for_gop(e, SCENE.gop_size, SCENE.fps).segment_ticks(e)
        seg.write_bytes(set_timeline(media, 2, ticks))  # GOP 1's place (in the tree's timescale): pictures differ
    async with serving(root) as url:
        log = await play(PlayConfig(url, codec="av1", qp=16, download=QUICK, view=VIEW))
    assert [g["rep"] for g in log["gops"]] == ["av1q16", "av1q41", "av1q16"]
    assert any(event in e for e in log["gops"][1]["events"]), log["gops"][1]["events"]


def test_a_tree_with_av1_alone_plays_and_simulates(scene, tmp_path):
    alone = tmp_path / "av1"
    pack(scene / "model", alone, PackConfig(ladder="fixed", codecs=("av1",), av1_qps=(16, 41), jobs=2), progress=False)
    ladder = load_ladder(str(alone))
    assert ladder.pres.feature_codec.name == "av1" and [r.rep_id for r in ladder.pres.ladder] == ["av1q41", "av1q16"]
    sc = scenario_from_dict({"scene": str(alone), "abr": ["throughput"], "effects": {"bandwidth": {"kbps": 1e5}},
                             "decode": {"frame_ms": {"av1": 1.0}}}, "av1", tmp_path)
    sim = simulate(ladder, sc, "throughput")
    assert sim["gops_played"] == SCENE.num_gops and all(g["rep"].startswith("av1q") for g in sim["gops"])
    (tmp_path / "s.toml").write_text(f'scene = "{alone}"\ncodec = "av1"\nabr = "mpc"\n')
    result = stgs("sim", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr


async def test_stgs_play_plays_a_tree_with_av1_alone(scene, tmp_path):
    import asyncio

    alone = tmp_path / "av1"
    pack(scene / "model", alone, PackConfig(ladder="fixed", codecs=("av1",), av1_qps=(24,), jobs=2), progress=False)
    async with serving(alone) as url:
        result = await asyncio.to_thread(stgs, "play", url, "--size", "32x24", "--log", str(tmp_path / "log.json"))
    assert result.returncode == 0, result.stderr
    assert "av1 rungs av1q24,av1q24,av1q24" in result.stdout
    assert json.loads((tmp_path / "log.json").read_text())["codec"] == "av1"
