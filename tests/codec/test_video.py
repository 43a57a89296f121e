"""The one ffmpeg route: frame-by-frame decoding, bounded reads, errors in ffmpeg's own words."""

import os
import tempfile

import numpy as np
import pytest

from stgs.codec import ffmpeg
from stgs.codec.mp4 import split_fragmented
from stgs.codec.video import VideoTiming, decode_segment, encode_gop, iter_frames

E, H, W = 6, 16, 32


@pytest.fixture(scope="module")
def segment():
    rng = np.random.default_rng(0)
    frames = (rng.integers(0, 4096, (E, H, W)) // 256 * 256).astype(np.uint16)  # coarse: near-lossless at QP 4
    init, media = split_fragmented(encode_gop(frames, 4, VideoTiming.for_gop(E, E, 6.0), "ultrafast"))
    return frames, init, media


def test_frames_one_at_a_time_equal_the_whole_decode(segment):
    frames, init, media = segment
    whole = decode_segment(init, media, E, H, W)
    assert whole.shape == (E, H, W) and np.abs(whole.astype(int) - frames).mean() < 64
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "s.mp4")
        with open(path, "wb") as f:
            f.write(init + media)
        one_by_one = list(iter_frames(path, E, H, W))
        assert len(one_by_one) == E and all((a == b).all() for a, b in zip(one_by_one, whole, strict=True))
        it = iter_frames(path, E, H, W)
        next(it)
        it.close()  # a caller that stops early: the decode is killed, nothing more is read
        with pytest.raises(ValueError, match="more than the 3 frames"):
            list(iter_frames(path, 3, H, W))
        with pytest.raises(ValueError, match=r"ended inside a frame|decodes to"):
            list(iter_frames(path, E, H, W + 1))


def test_reader_is_closed_when_the_caller_stops():
    reader = ffmpeg.FrameReader(["-f", "lavfi", "-i", "testsrc=size=32x16:rate=10", "-t", "100", "-f", "rawvideo",
                                 "-pix_fmt", "gray", "pipe:"], 32 * 16)
    with reader:
        first = next(iter(reader))
    assert len(first) == 32 * 16 and reader.proc.returncode is not None  # killed, not left running for 100 s


def test_errors_are_ffmpegs_own_words(tmp_path):
    with pytest.raises(ffmpeg.FFmpegError, match="ffmpeg failed"):
        ffmpeg.run(["-i", str(tmp_path / "missing.mp4"), "-f", "null", "-"])
    (tmp_path / "bad.mp4").write_bytes(b"\0" * 100)
    with pytest.raises(ValueError, match="does not decode"):
        list(iter_frames(str(tmp_path / "bad.mp4"), E, H, W))
