"""Keyframe container and MP4 segment handling, on real encodes."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch

from stgs.codec.attributes import SPECS
from stgs.codec.features import feature_ranges
from stgs.codec.keyframe import KeyframeError, decode_keyframe, encode_keyframe, quant_specs
from stgs.codec.mp4 import MP4Error, find_path, hevc_codecs, iter_boxes, set_timeline, split_fragmented
from stgs.codec.quant import KEYFRAME_RUNGS, LOSSLESS, KeyframeQuant
from stgs.codec.video import VideoTiming, decode_segment, encode_gop
from stgs.errors import FieldError
from stgs.model.gop import GOPShape
from tests.model.test_gop import random_model


@pytest.mark.parametrize("rung", ["fine", "coarse"])
def test_a_lossy_keyframe_round_trips_within_its_steps_and_says_its_quant(keyframe, rung):
    model, ranges, lossless = keyframe
    quant = KEYFRAME_RUNGS[rung]
    data = encode_keyframe(3, model, ranges, quant)
    assert len(data) < len(lossless)
    kf = decode_keyframe(data, model.shape, 3, len(data), quant)
    assert torch.equal(kf.feature_ranges, ranges)
    decoded = kf.to_model(model.features.detach())
    for spec in quant_specs(quant):
        want = getattr(model, spec.param).detach()
        want = want.clamp(*spec.clip) if spec.clip else want
        lo, hi = spec.clip or (float(want.min()), float(want.max()))
        step = (hi - lo) / (spec.levels - 1)
        assert (getattr(decoded, spec.param) - want).abs().max() <= step, spec.name
    for name, weight in model.field.state_dict().items():  # per-row codes: half a row's step off at most
        row_step = (weight.amax(1) - weight.amin(1)) / ((1 << quant.field) - 1)
        assert ((kf.field[name] - weight).abs() <= row_step[:, None] / 2 + 1e-6).all(), name
    # a decoder told another quantisation refuses it, either way round
    with pytest.raises(KeyframeError, match="quant"):
        decode_keyframe(data, model.shape, 3, len(data))
    with pytest.raises(KeyframeError, match="quant"):
        decode_keyframe(lossless, model.shape, 3, len(lossless), quant)
    other = KEYFRAME_RUNGS["coarse" if rung == "fine" else "fine"]
    with pytest.raises(KeyframeError, match="quant"):
        decode_keyframe(data, model.shape, 3, len(data), other)


def test_keyframe_quant_spelling_and_bounds():
    assert KeyframeQuant() == LOSSLESS and LOSSLESS.lossless and not KEYFRAME_RUNGS["coarse"].lossless
    assert [getattr(LOSSLESS, spec.name) for spec in SPECS] == [spec.levels.bit_length() - 1 for spec in SPECS]
    for quant in KEYFRAME_RUNGS.values():
        assert KeyframeQuant.parse(quant.value) == quant
    for bad, field in [("position=17;scale=4;rotation=4;opacity=3;color=6;field=4", "position"),
                       ("position=8;scale=4;rotation=4;opacity=3;color=6;field=9", "field"),
                       ("position=8;scale=4;rotation=4;opacity=3;color=6", "quant"),
                       ("position=8;position=8;scale=4;rotation=4;opacity=3;color=6;field=4", "quant"),
                       ("position=x;scale=4;rotation=4;opacity=3;color=6;field=4", "quant")]:
        with pytest.raises(FieldError) as info:
            KeyframeQuant.parse(bad)
        assert info.value.field == field


@pytest.fixture(scope="module")
def keyframe():
    model = random_model(n=16 * 16, gop_size=4)
    ranges = feature_ranges(model.features.detach())
    return model, ranges, encode_keyframe(3, model, ranges)


def test_keyframe_round_trip(keyframe):
    model, ranges, data = keyframe
    kf = decode_keyframe(data, model.shape, 3, max_bytes=len(data))
    assert torch.equal(kf.feature_ranges, ranges)
    for name, weight in model.field.state_dict().items():
        assert torch.equal(kf.field[name], weight)
    decoded = kf.to_model(model.features.detach())
    assert (decoded.xyz - model.xyz).abs().max() < 1e-3
    # to_model allocates without initialising: every parameter must have been written.
    original = dict(model.named_parameters())
    for name, param in decoded.named_parameters():
        assert torch.isfinite(param).all(), name
        if name.startswith("field.") or name == "features":
            assert torch.equal(param, original[name]), name
    for spec in SPECS:
        want = getattr(model, spec.param).detach()
        want = want.clamp(*spec.clip) if spec.clip else want
        lo, hi = spec.clip or (float(want.min()), float(want.max()))
        step = (hi - lo) / (spec.levels - 1)  # half a step off at most; a whole step allows for rounding
        assert (getattr(decoded, spec.param) - want).abs().max() <= step, spec.name
    with pytest.raises(ValueError, match="features must be"):
        kf.to_model(model.features.detach()[:-1])


def test_keyframe_checks(keyframe):
    model, _, data = keyframe
    with pytest.raises(KeyframeError, match="limit"):
        decode_keyframe(data, model.shape, 3, max_bytes=len(data) - 1)
    with pytest.raises(KeyframeError, match="gop"):
        decode_keyframe(data, model.shape, 4, max_bytes=len(data))
    other = GOPShape(capacity=model.shape.capacity, gop_size=5, window=3)
    with pytest.raises(KeyframeError, match="gop_size"):
        decode_keyframe(data, other, 3, max_bytes=len(data))
    with pytest.raises(KeyframeError):
        decode_keyframe(struct.pack("<Q", 1 << 40) + data[8:], model.shape, 3, max_bytes=len(data))
    corrupt = bytearray(data)
    corrupt[-200:] = b"\xff" * 200
    with pytest.raises(KeyframeError):
        decode_keyframe(bytes(corrupt), model.shape, 3, max_bytes=len(data))
    with pytest.raises(KeyframeError, match="truncated"):
        decode_keyframe(b"abc", model.shape, 3, max_bytes=100)


@pytest.fixture(scope="module")
def encoded():
    timing = VideoTiming.for_gop(8, 6, 24.0)
    yy, xx = np.mgrid[0:32, 0:32]
    frames = np.stack([2000 + 900 * np.sin(xx / 5 + i / 3) * np.cos(yy / 7) for i in range(8)]).astype(np.uint16)
    return timing, frames, encode_gop(frames, 20, timing)


def test_timing_spans_the_gop_exactly():
    t = VideoTiming.for_gop(62, 60, 30.0)
    assert t.rate == 31 and t.segment_ticks(62) / t.timescale == pytest.approx(2.0)
    t = VideoTiming.for_gop(32, 30, 29.97)
    assert t.segment_ticks(32) * 29.97 / t.timescale == pytest.approx(30, rel=1e-4)


def test_split_timeline_and_codecs(encoded):
    timing, frames, mp4 = encoded
    init, media = split_fragmented(mp4)
    assert [b.type for b in iter_boxes(init)] == ["ftyp", "moov"]
    assert [b.type for b in iter_boxes(media)] == ["styp", "moof", "mdat"]
    assert hevc_codecs(init).startswith("hvc1.4.")  # HEVC Range Extensions (12-bit 4:0:0)
    placed = set_timeline(media, 6, 5 * timing.segment_ticks(8))
    moof = find_path(placed, ["moof"])
    tfdt = find_path(placed, ["traf", "tfdt"], moof.body, moof.end)
    version = placed[tfdt.body]
    fmt = ">Q" if version == 1 else ">I"
    assert struct.unpack_from(fmt, placed, tfdt.body + 4)[0] == 5 * timing.segment_ticks(8)
    mfhd = find_path(placed, ["mfhd"], moof.body, moof.end)
    assert struct.unpack_from(">I", placed, mfhd.body + 4)[0] == 6
    decoded = decode_segment(init, placed, 8, 32, 32)
    assert decoded.shape == (8, 32, 32) and np.abs(decoded.astype(int) - frames).mean() < 20


def test_decoder_refuses_wrong_sizes(encoded):
    _, _, mp4 = encoded
    init, media = split_fragmented(mp4)
    with pytest.raises(ValueError, match="more than"):
        decode_segment(init, media, 4, 32, 32)
    with pytest.raises(ValueError, match="expected"):
        decode_segment(init, media, 9, 32, 32)
    with pytest.raises(ValueError, match="decode"):  # truncated: no frames, or an ffmpeg error
        decode_segment(init, media[:40], 8, 32, 32)


def test_box_parser_rejects_lies():
    with pytest.raises(MP4Error, match="claims"):
        list(iter_boxes(struct.pack(">I4s", 1000, b"moov") + b"x" * 10))
    with pytest.raises(MP4Error, match="truncated"):
        list(iter_boxes(b"\x00\x00"))
