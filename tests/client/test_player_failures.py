"""Whatever fails inside a playback ends it: one PlaybackError, the log written, no task left waiting.

Each case once left the renderer waiting forever on a future the failed task would never set."""

from __future__ import annotations

import asyncio
import json
import re
import struct

import pytest

from stgs.client import PlaybackError, PlayConfig, failure, play, resources, session
from stgs.client.config import ViewSpec
from stgs.codec import stream
from tests.client.conftest import QUICK, copy_tree, segment, serving

SMALL = ViewSpec(width=32, height=24)


async def test_a_defect_in_the_decoder_ends_the_playback_with_its_traceback_logged(scene, tmp_path, monkeypatch):
    def broken(frame, side, ranges, out=None, bits=12):
        raise TypeError("unsupported operand")  # stands in for any defect in the decoder thread

    monkeypatch.setattr(stream, "dequantize_frame", broken)
    async with serving(scene / "dash") as url:
        with pytest.raises(failure.InternalError, match="unexpectedly: TypeError: unsupported operand"):
            await asyncio.wait_for(play(PlayConfig(url, qp=32, download=QUICK, view=SMALL,
                                                   log=tmp_path / "log.json")), timeout=30)
    log = json.loads((tmp_path / "log.json").read_text())
    assert "TypeError" in log["error"] and "broken" in log["error_detail"]
    assert log["gops_played"] == 0


async def test_a_defect_in_the_fetcher_ends_the_playback(scene, tmp_path, monkeypatch):
    real = session.Session.drive

    async def broken(self, steps):
        if self.records[self.k0].rep:  # GOP 0 fetched: the next fetch fails
            raise KeyError("rung")
        return await real(self, steps)

    monkeypatch.setattr(session.Session, "drive", broken)
    async with serving(scene / "dash") as url:
        with pytest.raises(failure.InternalError, match="KeyError"):
            await asyncio.wait_for(play(PlayConfig(url, qp=32, download=QUICK, view=SMALL, out=tmp_path / "o.mp4",
                                                   log=tmp_path / "log.json")), timeout=30)
    assert not list(tmp_path.glob("*.mp4")) and not list(tmp_path.glob(".o.mp4*"))  # no half-written output
    assert json.loads((tmp_path / "log.json").read_text())["error_detail"]


async def test_a_keyframe_header_with_a_non_list_shape_is_a_keyframe_error(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    kf = segment(root, "v-*/keyframes/gop_00000.stgk")
    data = kf.read_bytes()
    size = struct.unpack_from("<Q", data)[0]
    header = json.loads(data[8:8 + size])
    name = next(k for k, v in header.items() if k != "__metadata__" and v["dtype"] == "F32")
    header[name]["shape"] = True
    raw = json.dumps(header).encode()
    kf.write_bytes(struct.pack("<Q", len(raw)) + raw + data[8 + size:])
    async with serving(root) as url:
        with pytest.raises(PlaybackError, match=f"keyframe segment of GOP 0: keyframe tensor {name} has shape True"):
            await asyncio.wait_for(play(PlayConfig(url, qp=32, download=QUICK, view=SMALL)), timeout=30)


def test_decoding_more_than_the_machine_holds_is_refused_before_fetching():
    gop = 1040 * 8192**2 * 2 + 1040 * 2048**2 * 16 * 4  # the caps: grid 2048, G 1024, W 16
    with pytest.raises(PlaybackError, match=r"decoding needs 780\.0 GiB \(2 GOPs of 390\.0 GiB at once\); "
                                            r"this machine has 16\.0 GiB"):
        resources.check_decode_memory(gop, 2, ram=16 << 30)
    resources.check_decode_memory(1 << 30, 2, ram=16 << 30)  # fits


async def test_a_scene_at_the_caps_is_refused_by_memory_not_a_crash(scene, tmp_path):
    """At the caps (4,194,304 Gaussians) a streamed GOP needs ~4 GiB; a ring of 512 feature frames of 256 MiB
    each is more than any machine here holds."""
    root = copy_tree(scene, tmp_path)
    mpd = root / "manifest.mpd"
    text = mpd.read_text()
    for key, value in (("capacity", 4194304), ("grid_side", 2048), ("gop_size", 1024), ("window", 16)):
        text, n = re.subn(rf'{key}=\d+', f"{key}={value}", text)
        assert n == 1, key
    mpd.write_text(text)
    async with serving(root) as url:
        with pytest.raises(PlaybackError, match=r"decoding needs .* GiB"):
            await asyncio.wait_for(play(PlayConfig(url, download=QUICK, view=SMALL, ring_frames=512)), timeout=30)
