"""Features streamed frame by frame through the player: the same pixels as the whole-GOP decode, exact drop
accounting in real time, seeking, and a feature segment that breaks mid-GOP."""

from __future__ import annotations

import gc
import threading
import time
import weakref

import cv2
import numpy as np
import pytest

from stgs.camera import read_scene_cameras
from stgs.client import PlayConfig, framepath, play
from stgs.client.config import ViewSpec
from stgs.codec import stream
from stgs.codec.keyframe import KeyframeError, KeyframeSegment
from stgs.codec.mp4 import set_timeline, split_fragmented
from stgs.codec.video import VideoTiming, decode_segment, encode_gop
from stgs.errors import FieldError
from stgs.fsio import to_uint8
from stgs.model.renderer import FrameRenderer
from stgs.model.store import load_model
from stgs.packaged import packaged_gops
from stgs.tree import rep_id
from tests.client.conftest import QUICK, SCENE, copy_tree, segment, serving

G = SCENE.gop_size
CAM = ViewSpec(camera="cam00")


def whole_gop_renderer(root, qp: int, k: int) -> FrameRenderer:
    """GOP k of the tree decoded the old way: every feature frame at once, then one model."""
    return FrameRenderer(packaged_gops(root)[rep_id(qp)](k))


def assert_frames_equal_whole_decode(scene, root, frames_dir, qp: int, expected: list[int]) -> None:
    cameras = read_scene_cameras(root)
    cam = next(c for c in cameras if c.name == "cam00")  # the camera the player draws from
    pngs = sorted(frames_dir.glob("*.png"))
    assert [int(p.stem) for p in pngs] == expected
    renderers = {}
    for png in pngs:
        f = int(png.stem)
        k = f // G
        renderers.setdefault(k, whole_gop_renderer(root, qp, k))
        local = to_uint8(renderers[k].render(f % G, cam).clamp(0, 1))
        streamed = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
        assert np.array_equal(streamed, local), f"frame {f} at QP {qp}"


@pytest.mark.parametrize("qp", [16, 24, 32])
async def test_streamed_frames_equal_the_whole_gop_decode_bit_for_bit(scene, tmp_path, qp):
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=qp, view=CAM, out=tmp_path / "f", download=QUICK, ring_frames=3))
    assert log["error"] is None and log["ring_frames"] == 3
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", qp, list(range(SCENE.num_gops * G)))
    for gop in log["gops"]:
        assert gop["ring_peak"] <= 3 and len(gop["decode_ms"]) == G + 2  # E = G + W - 1 frames, all decoded
        assert len(gop["wait_ms"]) == len(gop["deform_ms"]) == len(gop["splat_ms"]) == G


async def test_seeking_to_a_middle_gop_starts_with_its_first_frame(scene, tmp_path):
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=24, start_s=1.5, view=CAM, out=tmp_path / "f", download=QUICK))
    assert log["start_gop"] == 1 and [g["index"] for g in log["gops"]] == [1, 2]
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", 24, list(range(G, 3 * G)))


@pytest.mark.parametrize("ahead", [0, 2])
async def test_a_slow_renderer_drops_frames_and_the_count_is_exact(scene, tmp_path, monkeypatch, ahead):
    real = framepath.FramePath.render
    interval = 1 / SCENE.fps

    def slow(self, ready, i, camera, deadline):
        frame = real(self, ready, i, camera, deadline)
        time.sleep(1.6 * interval)  # every rendered frame overruns its slot
        return frame

    monkeypatch.setattr(framepath.FramePath, "render", slow)
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=32, realtime=True, view=CAM, out=tmp_path / "f", download=QUICK,
                                    ring_frames=3, render_ahead=ahead))
    rendered = sorted(int(p.stem) for p in (tmp_path / "f").glob("*.png"))
    frames = SCENE.num_gops * G
    assert log["frames"] == frames and log["rendered_frames"] == len(rendered)
    assert log["dropped_frames"] == frames - len(rendered)
    if ahead == 0:  # each frame in its own slot: ~1 in 2.6 frames is dropped
        assert frames / 4 <= log["dropped_frames"] <= frames * 3 / 4
    else:  # a head start cannot make up for a renderer slower than real time all along
        assert log["dropped_frames"] >= 2
    for gop in log["gops"]:
        assert gop["dropped"] + len(gop["render_ms"]) == G
        last = max(f % G for f in rendered if f // G == gop["index"])
        assert len(gop["decode_ms"]) >= last + 3  # decoded through the last drawn frame's window (W = 3)
    assert rendered[0] == 0  # the first frame of a GOP always has its slot
    # the frames drawn after drops have their own features: dropped frames' were consumed in order
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", 32, rendered)


@pytest.mark.parametrize("ahead", [0, 2])
async def test_rendering_ahead_absorbs_a_slow_first_frame_per_gop(scene, tmp_path, monkeypatch, ahead):
    """The first frame of every GOP takes 2.2 frame intervals, the others are fast: rendered in its own slot it
    makes the next frame miss its slot, once per GOP after the first (whose first frame is drawn before the
    clock starts); rendered up to two slots early it borrows the time the fast frames left."""
    real = framepath.FramePath.render
    interval = 1 / SCENE.fps

    def slow_first(self, ready, i, camera, deadline):
        frame = real(self, ready, i, camera, deadline)
        if i == 0:
            time.sleep(2.2 * interval)
        return frame

    monkeypatch.setattr(framepath.FramePath, "render", slow_first)
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=32, realtime=True, view=CAM, out=tmp_path / "f", download=QUICK,
                                    render_ahead=ahead))
    assert log["error"] is None and log["render_ahead"] == ahead and log["stalls"]["count"] == 0
    rendered = sorted(int(p.stem) for p in (tmp_path / "f").glob("*.png"))
    if ahead == 0:
        assert [f for f in range(SCENE.num_gops * G) if f not in rendered] == [G + 1, 2 * G + 1]
    else:
        assert log["dropped_frames"] == 0 and rendered == list(range(SCENE.num_gops * G))
        for gop in log["gops"][1:]:  # drawn before its slot: a GOP's first frame during the GOP before
            assert gop["render_at_s"][0] < gop["play_start_s"] - interval
    # the first frame is shown once it is rendered, 2.2 intervals after the GOP is ready: start-up counts that
    assert log["time_to_first_frame_s"] >= log["startup_delay_s"] + 2.2 * interval
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", 32, rendered)


@pytest.mark.parametrize("ahead", [0, 2])
async def test_a_slow_first_frame_of_the_playback_sets_the_clock(scene, tmp_path, monkeypatch, ahead):
    """The playback's first frame takes 4.5 frame intervals (a cold start), every other frame is fast: the clock
    starts once it is drawn, so it takes no slot from the frames after it (started two slots after the GOP was
    ready, frame 1 would miss its slot), and start-up is when it is shown."""
    real = framepath.FramePath.render
    interval = 1 / SCENE.fps
    slow = []

    def slow_first(self, ready, i, camera, deadline):
        frame = real(self, ready, i, camera, deadline)
        if not slow:
            slow.append((ready.index, i))
            time.sleep(4.5 * interval)
        return frame

    monkeypatch.setattr(framepath.FramePath, "render", slow_first)
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=32, realtime=True, view=CAM, out=tmp_path / "f", download=QUICK,
                                    render_ahead=ahead, start_s=1.0))
    assert log["error"] is None and slow == [(1, 0)] and log["stalls"]["count"] == 0
    assert log["dropped_frames"] == 0, [g["dropped"] for g in log["gops"]]
    first = log["gops"][0]
    assert first["play_start_s"] - first["boundary_wait_s"] >= 4.5 * interval  # the clock waited for frame 0
    assert log["time_to_first_frame_s"] >= log["startup_delay_s"] + 4.5 * interval
    rendered = sorted(int(p.stem) for p in (tmp_path / "f").glob("*.png"))
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", 32, rendered)


async def test_a_played_gop_is_let_go(scene):
    """Memory does not grow with the playback's length: by the time GOP 2 plays, GOP 0's renderer (and the
    model, feature stream and segment bytes that come with it) has been freed."""
    renderers: dict[int, weakref.ref] = {}
    alive: list[bool] = []

    def probe(k, i, renderer, window):
        renderers.setdefault(k, weakref.ref(renderer))
        if k == 2 and i == G - 1:
            gc.collect()
            alive.append(renderers[0]() is not None)

    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=32, view=CAM, download=QUICK), on_frame=probe)
    assert log["error"] is None and len(renderers) == SCENE.num_gops == 3
    assert alive == [False]


def test_render_ahead_is_a_whole_number_of_slots():
    with pytest.raises(FieldError, match="render_ahead"):
        PlayConfig("http://127.0.0.1/manifest.mpd", render_ahead=-1).validate()


def shortened(media: bytes, init: bytes, shape, fps: float, k: int, qp: int, keep: int) -> bytes:
    """GOP k's feature segment re-encoded with only its first `keep` frames, at GOP k's place in the timeline."""
    side = shape.grid_side
    frames = decode_segment(init, media, shape.num_features, 4 * side, 4 * side)
    timing = VideoTiming.for_gop(shape.num_features, shape.gop_size, fps)
    _, short = split_fragmented(encode_gop(frames[:keep], qp, timing, "medium"))  # the packer's preset: its SPS
    return set_timeline(short, k + 1, k * timing.segment_ticks(shape.num_features))


async def test_a_feature_segment_that_ends_mid_gop_falls_back_from_that_frame(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    meta, _ = load_model(scene / "model")
    seg = segment(root, "v-*/features/qp16/seg_00001.m4s")
    init = segment(root, "v-*/features/qp16/init.mp4").read_bytes()
    seg.write_bytes(shortened(seg.read_bytes(), init, meta.shape, SCENE.fps, 1, 16, keep=5))
    async with serving(root) as url:
        log = await play(PlayConfig(url, qp=16, view=CAM, out=tmp_path / "f", download=QUICK, ring_frames=3))
    assert log["error"] is None and log["rendered_frames"] == SCENE.num_gops * G
    events = log["gops"][1]["events"]
    assert any("fallback from qp16" in e and "decodes to 5 frames" in e for e in events), events
    assert any("resumes at frame 3" in e for e in events), events  # frames 3..5 are the first window past 5
    assert [g["qp"] for g in log["gops"]] == [16, 32, 16]


async def test_the_first_feature_frames_decode_while_the_keyframe_does(scene, tmp_path, monkeypatch):
    """The feature stream starts from the keyframe's header, before its images decode: a keyframe decode
    that waits for the stream's first frame finishes (sequentially it would wait for ever)."""
    first_frame = threading.Event()
    real_frames, real_decode = stream.iter_frames, KeyframeSegment.decode
    overlapped = []

    def frames(*args, **kwargs):
        for frame in real_frames(*args, **kwargs):
            first_frame.set()
            yield frame

    def decode(self):
        if not overlapped:  # the first keyframe; a later one (the next GOP's, decoded ahead) need not wait
            overlapped.append(first_frame.wait(timeout=20))
        return real_decode(self)

    monkeypatch.setattr(stream, "iter_frames", frames)
    monkeypatch.setattr(KeyframeSegment, "decode", decode)
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=32, view=CAM, out=tmp_path / "f", download=QUICK, duration_s=1.0))
    assert log["error"] is None and overlapped == [True]
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", 32, list(range(G)))


async def test_a_keyframe_that_fails_to_decode_once_restarts_its_feature_stream(scene, tmp_path, monkeypatch):
    """GOP 1's keyframe images fail on the first try, after its feature stream has started: the keyframe is
    downloaded again, the stream restarted, and every frame is still the whole-GOP decode's."""
    real_decode = KeyframeSegment.decode
    failures = []

    def flaky(self):
        if self.gop == 1 and not failures:
            failures.append(self.gop)
            raise KeyframeError("keyframe image position: test failure")
        return real_decode(self)

    monkeypatch.setattr(KeyframeSegment, "decode", flaky)
    async with serving(scene / "dash") as url:
        log = await play(PlayConfig(url, qp=24, view=CAM, out=tmp_path / "f", download=QUICK, ring_frames=3))
    assert log["error"] is None and failures == [1]
    assert any("test failure" in e for e in log["gops"][1]["events"]), log["gops"][1]["events"]
    assert [r["kind"] for r in log["gops"][1]["requests"]].count("keyframe") == 2
    assert_frames_equal_whole_decode(scene, scene / "dash", tmp_path / "f", 24, list(range(SCENE.num_gops * G)))
