"""Feature video: 12-bit gray HEVC (libx265) through ffmpeg (stgs.codec.ffmpeg), one closed GOP per segment.

Encoding settings (constant QP, closed GOP, IDR at the first frame, no scene
cuts, keyint = E, one x265 thread pool per encode, bit-exact muxing) make each
GOP's segment decodable alone after the init segment, and make a re-encode of
the same frames produce the same bytes.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from stgs.codec import ffmpeg
from stgs.errors import StgsError

PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow")
"""x265 presets, fastest first."""


@dataclass(frozen=True)
class VideoTiming:
    """How a GOP's E feature frames map onto its playback time."""

    rate: Fraction
    """Video frame rate: E frames span exactly G / fps seconds."""
    timescale: int
    """MP4 ticks per second."""
    frame_ticks: int
    """Ticks per video frame."""

    @classmethod
    def for_gop(cls, num_features: int, gop_size: int, fps: float) -> VideoTiming:
        fps_frac = Fraction(fps).limit_denominator(1001)
        rate = Fraction(num_features) * fps_frac / gop_size
        scale = 1
        while rate.numerator * scale < 1000:  # a timescale of at least 1 kHz
            scale *= 2
        return cls(rate, rate.numerator * scale, rate.denominator * scale)

    def segment_ticks(self, num_features: int) -> int:
        return num_features * self.frame_ticks


def x265_params(qp: int, keyint: int, crf: bool = False) -> str:
    """x265 settings; crf=True uses the value as a CRF instead of a constant QP (benchmarks only)."""
    return ":".join([f"{'crf' if crf else 'qp'}={qp}", f"keyint={keyint}", f"min-keyint={keyint}", "scenecut=0",
                     "open-gop=0", "info=0", "pools=1", "frame-threads=1", "lookahead-threads=0",
                     "log-level=error"])


def encode_gop(frames: np.ndarray, qp: int, timing: VideoTiming, preset: str = "medium",
               crf: bool = False) -> bytes:
    """(E, H, W) uint16 12-bit frames -> a single-fragment fragmented MP4 (HEVC Rext, gray 12-bit)."""
    if frames.ndim != 3 or frames.dtype != np.uint16:
        raise ValueError("encode_gop takes (E, H, W) uint16 frames")
    if preset not in PRESETS:
        raise StgsError(f"unknown x265 preset {preset!r}; choose from {', '.join(PRESETS)}")
    e, h, w = frames.shape
    with tempfile.TemporaryDirectory() as tmp:
        out_path = os.path.join(tmp, "gop.mp4")
        args = ["-threads", "1", "-f", "rawvideo", "-pix_fmt", "gray12le", "-s", f"{w}x{h}",
                "-framerate", f"{timing.rate.numerator}/{timing.rate.denominator}", "-i", "pipe:",
                "-f", "mp4", "-c:v", "libx265", "-pix_fmt", "gray12le", "-preset", preset,
                "-x265-params", x265_params(qp, e, crf), "-tag:v", "hvc1",
                "-movflags", "+frag_keyframe+empty_moov+default_base_moof", "-fflags", "+bitexact",
                "-flags:v", "+bitexact", "-map_metadata", "-1", "-video_track_timescale", str(timing.timescale),
                "-frag_duration", "2000000000", "-y", out_path]
        try:
            ffmpeg.run(args, np.ascontiguousarray(frames, dtype="<u2").tobytes())
        except ffmpeg.FFmpegError as exc:
            raise RuntimeError(f"ffmpeg encode failed: {exc}") from exc
        with open(out_path, "rb") as f:
            return f.read()


def iter_frames(path: str, frames: int, height: int, width: int) -> Iterator[np.ndarray]:
    """The frames of the feature video at `path` ((H, W) uint16 each), decoded one at a time; raises ValueError
    for a video that does not decode, ends inside a frame, or holds more than `frames` frames (the extra frame is
    never read whole)."""
    frame_bytes = height * width * 2
    args = ["-i", path, "-f", "rawvideo", "-pix_fmt", "gray12le", "-fps_mode", "passthrough", "pipe:"]
    count = 0
    with ffmpeg.FrameReader(args, frame_bytes) as reader:
        try:
            for data in reader:
                if count == frames:
                    raise ValueError(f"feature segment holds more than the {frames} frames of {width}x{height} "
                                     "announced")
                count += 1
                yield np.frombuffer(data, dtype="<u2").reshape(height, width).astype(np.uint16)
        except ffmpeg.FFmpegError as exc:
            raise ValueError(f"feature segment does not decode: {exc}") from None
    if count != frames:
        raise ValueError(f"feature segment decodes to {count} frames, expected {frames} of {width}x{height}")


def decode_segment(init: bytes, media: bytes, frames: int, height: int, width: int) -> np.ndarray:
    """init + one media segment -> (frames, H, W) uint16, decoded frame by frame (at most one frame beyond those
    announced is ever requested from ffmpeg, so a hostile segment cannot make the decoder allocate more)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "segment.mp4")
        with open(path, "wb") as f:
            f.write(init)
            f.write(media)
        out = np.empty((frames, height, width), np.uint16)
        for i, frame in enumerate(iter_frames(path, frames, height, width)):
            out[i] = frame  # iter_frames stops before a frame past `frames`
    return out
