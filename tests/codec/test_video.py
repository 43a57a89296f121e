"""The one video route (PyAV in-process): deterministic encodes, frame-by-frame decoding, and hostile or mismatched
segments refused before a picture is decoded or converted."""

import io

import av
import numpy as np
import pytest

from stgs.codec.mp4 import split_fragmented
from stgs.codec.video import VideoError, VideoTiming, decode_segment, encode_gop, iter_frames
from tests.conftest import LOOP_FILTERS_OFF, loop_filter_flags

E, H, W = 6, 16, 32


@pytest.fixture(scope="module")
def segment():
    rng = np.random.default_rng(0)
    frames = (rng.integers(0, 4096, (E, H, W)) // 256 * 256).astype(np.uint16)  # coarse: near-lossless at QP 4
    data = encode_gop(frames, 4, VideoTiming.for_gop(E, E, 6.0), "ultrafast")
    init, media = split_fragmented(data)
    return frames, data, init, media


def test_encode_is_deterministic_whatever_ran_before():
    """libx265 reads memory it never wrote: without the filled heap, the second and later encodes of a process
    gave other bytes (and, from PyAV's wrapper, garbage decode timestamps)."""
    rng = np.random.default_rng(1)
    noisy = rng.integers(0, 4096, (8, 64, 64)).astype(np.uint16)  # noise: motion search explores widely
    timing = VideoTiming.for_gop(8, 6, 30.0)
    first = encode_gop(noisy, 16, timing, "medium")
    for other in range(3):
        encode_gop(rng.integers(0, 4096, (4, 32, 48)).astype(np.uint16), 20 + other, timing, "fast")
        assert encode_gop(noisy, 16, timing, "medium") == first
    assert encode_gop(noisy, 30, timing, "medium") != first


def test_loop_filters_off_is_in_the_stream_and_decodes(tmp_path):
    rng = np.random.default_rng(2)
    frames = (rng.integers(0, 16, (E, 64, 64)) * 256).astype(np.uint16)
    timing = VideoTiming.for_gop(E, E, 6.0)
    with_filters = encode_gop(frames, 24, timing, "medium")
    without = encode_gop(frames, 24, timing, "medium", loop_filters=False)
    assert loop_filter_flags(with_filters, tmp_path / "on.mp4")["sample_adaptive_offset_enabled_flag"] == "1"
    assert loop_filter_flags(without, tmp_path / "off.mp4") == LOOP_FILTERS_OFF
    decoded = decode_segment(*split_fragmented(without), E, 64, 64)
    assert np.abs(decoded.astype(int) - frames).mean() < 256
    assert encode_gop(frames, 24, timing, "medium", loop_filters=False) == without


def test_frames_one_at_a_time_equal_the_whole_decode(segment):
    frames, data, init, media = segment
    whole = decode_segment(init, media, E, H, W)
    assert whole.shape == (E, H, W) and whole.dtype == np.uint16 and np.abs(whole.astype(int) - frames).mean() < 64
    one_by_one = list(iter_frames(data, E, H, W, threads=1))
    assert len(one_by_one) == E and all((a == b).all() for a, b in zip(one_by_one, whole, strict=True))
    it = iter_frames(data, E, H, W)
    next(it)
    it.close()  # a caller that stops early: the container is closed, nothing more is decoded


def test_frame_count_and_size_must_match_the_announcement(segment):
    _, data, _, _ = segment
    with pytest.raises(VideoError, match="more than the 3 frames"):
        list(iter_frames(data, 3, H, W))
    with pytest.raises(VideoError, match=f"decodes to {E} frames, expected {E + 1}"):
        list(iter_frames(data, E + 1, H, W))
    with pytest.raises(VideoError, match=f"is {W}x{H}, expected {W + 1}x{H}"):
        list(iter_frames(data, E, H, W + 1))


def _foreign_video(width: int, height: int, pix_fmt: str, tag: str) -> bytes:
    """Two frames of libx265 at another size or pixel format, fragmented like a feature video."""
    buf = io.BytesIO()
    with av.open(buf, "w", format="mp4", options={"movflags": "+frag_keyframe+empty_moov+default_base_moof"}) as out:
        stream = out.add_stream("libx265", rate=2, options={"x265-params": "log-level=error:keyint=2:bframes=0"})
        stream.width, stream.height, stream.pix_fmt, stream.codec_tag = width, height, pix_fmt, tag
        for i in range(2):
            frame = av.VideoFrame.from_ndarray(np.full((height, width), 1000, np.uint16), format="gray12le")
            frame = frame.reformat(format=pix_fmt)
            frame.pts = i
            out.mux(stream.encode(frame))
        out.mux(stream.encode(None))
    return buf.getvalue()


def test_a_stream_of_another_pixel_format_is_refused():
    with pytest.raises(VideoError, match=f"is {W}x{H} yuv420p, expected {W}x{H} gray12le"):
        list(iter_frames(_foreign_video(W, H, "yuv420p", "hvc1"), 2, H, W))


def test_in_band_parameter_sets_cannot_grow_the_picture(segment):
    """A media segment carrying its own parameter sets (hev1) for 512² pictures behind the 32x16 init segment is
    refused; no 512² frame ever reaches the caller (the decoder also runs with max_pixels set to the announced
    size)."""
    _, _, init, _ = segment
    _, big = split_fragmented(_foreign_video(512, 512, "gray12le", "hev1"))
    seen = []
    with pytest.raises(VideoError):
        for frame in iter_frames(init + big, 2, H, W):
            seen.append(frame.shape)
    assert all(shape == (H, W) for shape in seen)


def test_garbage_and_truncation_are_video_errors(segment):
    _, _, init, media = segment
    with pytest.raises(VideoError, match="does not decode"):
        list(iter_frames(b"\0" * 100, E, H, W))
    with pytest.raises(VideoError):
        decode_segment(init, media[:40], E, H, W)
    with pytest.raises(VideoError):
        decode_segment(b"", media, E, H, W)
