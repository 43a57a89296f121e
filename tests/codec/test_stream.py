"""The feature stream: frame-by-frame decode into a bounded ring, bit-exact against the whole-GOP decode, chained
across GOPs, and a broken or closed stream ends a waiting renderer instead of hanging it."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

from stgs.codec.features import feature_ranges, features_from_frames, quantize_features, tile_frames
from stgs.codec.mp4 import split_fragmented
from stgs.codec.stream import FeatureStream, StreamClosedError
from stgs.codec.video import VideoError, VideoTiming, decode_segment, encode_gop

SIDE, WINDOW = 8, 3


def feature_video(frames: int, seed: int = 0, qp: int = 20) -> tuple[bytes, torch.Tensor, torch.Tensor]:
    """A smooth random feature video of `frames` frames: (init + media, ranges, whole-GOP decoded features)."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, frames)[:, None, None]
    feats = torch.sin(6 * t + torch.rand(1, SIDE * SIDE, 16, generator=gen) * 6) + 0.1 * torch.rand(
        frames, SIDE * SIDE, 16, generator=gen)
    ranges = feature_ranges(feats)
    tiled = tile_frames(quantize_features(feats, ranges), SIDE).numpy().astype(np.uint16)
    data = encode_gop(tiled, qp, VideoTiming.for_gop(frames, frames - WINDOW + 1, 30.0), "ultrafast")
    init, media = split_fragmented(data)
    whole = features_from_frames(decode_segment(init, media, frames, 4 * SIDE, 4 * SIDE), SIDE, ranges)
    return data, ranges, whole


@pytest.fixture(scope="module")
def long_gop():
    return feature_video(240 + WINDOW - 1)


def play_through(stream: FeatureStream, frames: int, held: list[int] | None = None) -> list[torch.Tensor]:
    """Consume every frame's window in order, as the renderer does; returns each frame's first feature frame."""
    firsts = []
    for i in range(frames - WINDOW + 1):
        window = stream.window(i, WINDOW)
        firsts.append(window[0].clone())
        if i == frames - WINDOW:
            firsts += [w.clone() for w in window[1:]]
        if held is not None:
            held.append(len(stream._held))
        stream.release(i + 1)
    return firsts


def test_a_long_gop_streams_bit_exact_features_in_a_bounded_ring(long_gop):
    data, ranges, whole = long_gop
    frames = whole.shape[0]
    stream = FeatureStream(data, frames, SIDE, ranges, capacity=8).start()
    held: list[int] = []
    got = play_through(stream, frames, held)
    stream.join(10)
    assert len(got) == frames
    assert all(torch.equal(g, w) for g, w in zip(got, whole, strict=True))  # bit-exact, frame by frame
    assert stream.peak_held <= 8 and max(held) <= 8
    assert len(stream.decode_ms) == frames and stream.finished and stream.error is None


def test_the_next_gop_decodes_only_after_this_one_and_memory_stays_bounded_at_the_boundary():
    first, r1, w1 = feature_video(12, seed=1)
    second, r2, w2 = feature_video(12, seed=2)
    a = FeatureStream(first, 12, SIDE, r1, capacity=4).start()
    b = FeatureStream(second, 12, SIDE, r2, capacity=4).start(after=a)
    time.sleep(0.3)  # b may not decode while a has frames left to decode
    assert not a.finished and b.decode_ms == [] and a.peak_held == 4
    got_a = play_through(a, 12)
    a.join(10)
    got_b = play_through(b, 12)
    assert all(torch.equal(g, w) for g, w in zip(got_a + got_b, [*w1, *w2], strict=True))
    assert a.peak_held <= 4 and b.peak_held <= 4


def test_frames_released_before_they_are_decoded_are_not_dequantised(long_gop):
    data, ranges, whole = long_gop
    stream = FeatureStream(data, whole.shape[0], SIDE, ranges, capacity=4)
    stream.release(100)  # a renderer that dropped frames 0..99 before the decoder reached them
    stream.start()
    window = stream.window(100, WINDOW)
    assert all(torch.equal(w, whole[100 + j]) for j, w in enumerate(window))
    with pytest.raises(ValueError, match="already released"):
        stream.window(50, WINDOW)
    stream.close()
    stream.join(10)
    assert stream.dequantise_ms[:100] == [0.0] * 100 and min(stream.dequantise_ms[100:103]) > 0


def test_a_truncated_segment_serves_its_frames_then_raises():
    data, ranges, whole = feature_video(10)
    stream = FeatureStream(data, 14, SIDE, ranges, capacity=4).start()  # announced 14, holds 10
    assert all(torch.equal(w, whole[7 + j]) for j, w in enumerate(play_through_to(stream, 7)))  # frames 7..9
    stream.release(8)
    with pytest.raises(VideoError, match="decodes to 10 frames, expected 14"):
        stream.window(8, WINDOW, timeout=10)
    assert stream.finished


def play_through_to(stream: FeatureStream, i: int) -> list[torch.Tensor]:
    for j in range(i):
        stream.window(j, WINDOW, timeout=10)
        stream.release(j + 1)
    return stream.window(i, WINDOW, timeout=10)


def test_garbage_is_a_video_error_at_the_first_window():
    _, ranges, _ = feature_video(6)
    stream = FeatureStream(b"\0" * 500, 6, SIDE, ranges).start()
    with pytest.raises(VideoError):
        stream.window(0, WINDOW, timeout=10)


def test_a_waiting_renderer_gets_none_at_its_deadline_and_an_error_when_closed():
    data, ranges, _ = feature_video(8)
    a = FeatureStream(data, 8, SIDE, ranges, capacity=4).start()
    b = FeatureStream(data, 8, SIDE, ranges).start(after=a)  # waits for a, whose ring nobody drains
    a.window(0, WINDOW, timeout=10)
    start = time.perf_counter()
    assert b.window(0, WINDOW, timeout=0.2) is None
    assert 0.15 < time.perf_counter() - start < 2
    errors = []

    def wait():
        try:
            b.window(0, WINDOW)
        except StreamClosedError as exc:
            errors.append(exc)

    waiter = threading.Thread(target=wait)
    waiter.start()
    time.sleep(0.1)
    b.close()
    a.close()
    waiter.join(5)
    assert not waiter.is_alive() and len(errors) == 1
    a.join(5)
    b.join(5)
    assert a.finished and b.finished


def test_bad_requests_are_value_errors():
    data, ranges, _ = feature_video(6)
    with pytest.raises(ValueError, match="at least one frame"):
        FeatureStream(data, 6, SIDE, ranges, capacity=0)
    stream = FeatureStream(data, 6, SIDE, ranges, capacity=2)
    with pytest.raises(ValueError, match="outside the GOP"):
        stream.window(5, WINDOW)
    with pytest.raises(ValueError, match="does not fit a ring of 2"):
        stream.window(0, WINDOW)
