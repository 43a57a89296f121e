"""The AV1 10-bit feature video (the browsers' set): codes round-trip through the luma plane, re-encodes are
byte-identical in one process and across processes, its @codecs comes from the av1C box, and a segment of the
wrong codec, size, bit depth or length is refused with one clear VideoError."""

import hashlib
import io
import subprocess
import sys

import av
import numpy as np
import pytest

from stgs.codec.av1 import av1_codecs
from stgs.codec.features import code_max, dequantize_frame, feature_ranges, quantize_features, tile_frames
from stgs.codec.mp4 import MP4Error, split_fragmented
from stgs.codec.video import AV1, HEVC, VideoError, VideoTiming, decode_segment, encode_gop, iter_frames

E, SIDE = 8, 16
H = W = 4 * SIDE
TIMING = VideoTiming.for_gop(E, E - 2, 30.0)


def smooth_frames(seed: int = 0, e: int = E, h: int = H, w: int = W, bits: int = 10) -> np.ndarray:
    """Smooth moving ramps: what PLAS-sorted features look like, so a low QP is near-lossless."""
    y, x = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 6, 3)
    frames = [(np.sin(x / 9 + phase[0] + t / 7) * np.cos(y / 11 + phase[1]) + 1) / 2 for t in range(e)]
    return np.round(np.stack(frames) * code_max(bits)).astype(np.uint16)


@pytest.fixture(scope="module")
def segment():
    frames = smooth_frames()
    data = encode_gop(frames, 8, TIMING, codec=AV1)
    return frames, data, *split_fragmented(data)


def test_codes_round_trip_through_the_luma_plane(segment):
    frames, data, init, media = segment
    decoded = decode_segment(init, media, E, H, W, codec=AV1)
    assert decoded.dtype == np.uint16 and decoded.shape == (E, H, W) and decoded.max() <= 1023
    assert np.abs(decoded.astype(int) - frames).mean() < 4  # QP 8 of smooth content: within a few codes
    one_by_one = list(iter_frames(data, E, H, W, threads=1, codec=AV1))
    assert all(np.array_equal(a, b) for a, b in zip(one_by_one, decoded, strict=True))


def test_codecs_string_and_bit_depth_come_from_av1c(segment):
    _, _, init, _ = segment
    codecs = av1_codecs(init)
    assert codecs.startswith("av01.0.") and codecs.endswith("M.10") and len(codecs.split(".")) == 4
    assert AV1.codecs(init) == codecs
    hevc_init = split_fragmented(encode_gop((smooth_frames() * 4).astype(np.uint16), 20, TIMING, "ultrafast"))[0]
    with pytest.raises(MP4Error, match="no AV1 sample entry"):
        av1_codecs(hevc_init)


def test_reencode_is_byte_identical_in_one_process_whatever_ran_between(segment):
    frames, data, _, _ = segment
    encode_gop(smooth_frames(3, 4, 32, 48), 30, TIMING, "10", codec=AV1)
    encode_gop((smooth_frames(4) * 4).astype(np.uint16), 24, TIMING, "ultrafast")  # an HEVC encode between
    assert encode_gop(frames, 8, TIMING, codec=AV1) == data
    assert encode_gop(frames, 9, TIMING, codec=AV1) != data


def test_reencode_is_byte_identical_across_processes(segment):
    _, data, _, _ = segment
    script = ("import hashlib, sys; from tests.codec.test_av1 import smooth_frames, TIMING; "
              "from stgs.codec.video import AV1, encode_gop; "
              "sys.stdout.write(hashlib.sha256(encode_gop(smooth_frames(), 8, TIMING, codec=AV1)).hexdigest())")
    digests = {subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
               for _ in range(2)}
    assert digests == {hashlib.sha256(data).hexdigest()}


def test_ten_bit_codes_dequantise_over_the_same_ranges():
    import torch

    features = torch.linspace(-3, 5, E * SIDE * SIDE * 16).reshape(E, SIDE * SIDE, 16)
    ranges = feature_ranges(features)
    codes10 = tile_frames(quantize_features(features, ranges, 10), SIDE).numpy().astype(np.uint16)
    assert codes10.max() == 1023
    back = torch.stack([dequantize_frame(f, SIDE, ranges, bits=10) for f in codes10])
    step = (ranges[1] - ranges[0]) / 1023
    assert ((back - features).abs() <= step / 2 + 1e-5).all()
    with pytest.raises(ValueError, match="10 or 12 bits"):
        quantize_features(features, ranges, 8)


def test_a_segment_of_the_wrong_codec_or_size_is_refused(segment):
    _, _, init, media = segment
    with pytest.raises(VideoError, match="expected 64x48"):
        decode_segment(init, media, E, 48, 64, codec=AV1)
    with pytest.raises(VideoError, match=r"is (libdav1d|av1), expected hevc"):
        decode_segment(init, media, E, H, W, codec=HEVC)
    hevc = encode_gop((smooth_frames() * 4).astype(np.uint16), 20, TIMING, "ultrafast")
    with pytest.raises(VideoError, match="expected av1"):
        list(iter_frames(hevc, E, H, W, codec=AV1))


def test_an_eight_bit_av1_segment_is_refused_before_a_frame_is_kept():
    """A tree whose AV1 segment is 8-bit (another encoder, a tampered file) does not carry 10-bit codes."""
    out = io.BytesIO()
    with av.open(out, "w", format="mp4", options={"movflags": "+frag_keyframe+empty_moov+default_base_moof"}) as c:
        stream = c.add_stream("libsvtav1", rate=30, options={"preset": "12"})
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        for i in range(E):
            frame = av.VideoFrame.from_ndarray(np.full((H * 3 // 2, W), 100, np.uint8), format="yuv420p")
            frame.pts = i
            c.mux(stream.encode(frame))
        c.mux(stream.encode(None))
    with pytest.raises(VideoError, match="is 64x64 yuv420p, expected 64x64 yuv420p10le \\(10-bit av1\\)"):
        list(iter_frames(out.getvalue(), E, H, W, codec=AV1))


def test_truncated_garbage_and_miscounted_segments_are_video_errors(segment):
    _, _, init, media = segment
    with pytest.raises(VideoError):
        decode_segment(init, media[: len(media) // 2], E, H, W, codec=AV1)
    with pytest.raises(VideoError):
        decode_segment(init, b"\0" * 300, E, H, W, codec=AV1)
    with pytest.raises(VideoError, match="more than the 5 frames"):
        decode_segment(init, media, 5, H, W, codec=AV1)
    with pytest.raises(VideoError, match="decodes to 8 frames, expected 9"):
        decode_segment(init, media, 9, H, W, codec=AV1)


def test_an_odd_grid_side_encodes():
    """4S is a multiple of 4, not of 8, for an odd S (e.g. a 215 x 215 grid): SVT-AV1 pads internally."""
    frames = smooth_frames(5, 4, 4 * 13, 4 * 13)
    data = encode_gop(frames, 20, VideoTiming.for_gop(4, 2, 30.0), codec=AV1)
    decoded = decode_segment(*split_fragmented(data), 4, 52, 52, codec=AV1)
    assert np.abs(decoded.astype(int) - frames).mean() < 8
