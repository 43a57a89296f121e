"""Feature video: 12-bit gray HEVC (libx265) through ffmpeg, one closed GOP per segment.

Encoding settings (constant QP, closed GOP, IDR at the first frame, no scene
cuts, keyint = E, one x265 thread pool per encode, bit-exact muxing) make each
GOP's segment decodable alone after the init segment, and make a re-encode of
the same frames produce the same bytes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from fractions import Fraction

import ffmpeg
import numpy as np

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


def require_ffmpeg() -> None:
    if shutil.which("ffmpeg") is None or shutil.which("ffprobe") is None:
        raise StgsError("ffmpeg and ffprobe are required (Debian: apt-get install ffmpeg)")


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
        stream = (
            ffmpeg.input("pipe:", format="rawvideo", pix_fmt="gray12le", s=f"{w}x{h}",
                         framerate=f"{timing.rate.numerator}/{timing.rate.denominator}")
            .output(out_path, format="mp4", vcodec="libx265", pix_fmt="gray12le", preset=preset,
                    **{"x265-params": x265_params(qp, e, crf), "tag:v": "hvc1",
                       "movflags": "+frag_keyframe+empty_moov+default_base_moof",
                       "fflags": "+bitexact", "flags:v": "+bitexact", "map_metadata": "-1",
                       "video_track_timescale": timing.timescale, "frag_duration": 2_000_000_000})
            .global_args("-hide_banner", "-nostdin", "-loglevel", "error", "-threads", "1")
        )
        try:
            stream.run(input=np.ascontiguousarray(frames, dtype="<u2").tobytes(), capture_stdout=True,
                       capture_stderr=True, overwrite_output=True)
        except ffmpeg.Error as exc:
            raise RuntimeError(f"ffmpeg encode failed: {exc.stderr.decode(errors='replace').strip()}") from exc
        with open(out_path, "rb") as f:
            return f.read()


def decode_segment(init: bytes, media: bytes, frames: int, height: int, width: int) -> np.ndarray:
    """init + one media segment -> (frames, H, W) uint16.

    At most the expected number of bytes (+1 to detect extra frames) is read
    from ffmpeg, so a hostile segment cannot make the decoder allocate more.
    """
    expected = frames * height * width * 2
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "segment.mp4")
        with open(path, "wb") as f:
            f.write(init)
            f.write(media)
        cmd = ["ffmpeg", "-hide_banner", "-nostdin", "-loglevel", "error", "-i", path,
               "-f", "rawvideo", "-pix_fmt", "gray12le", "-fps_mode", "passthrough", "pipe:"]
        with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
            data = proc.stdout.read(expected + 1)
            extra = len(data) > expected
            if extra:
                proc.kill()
            err = proc.stderr.read(1 << 16)
            code = proc.wait()
    if extra:
        raise ValueError(f"feature segment holds more than the {frames} frames of {width}x{height} announced")
    if code != 0:
        raise ValueError(f"feature segment does not decode: {err.decode(errors='replace').strip()}")
    if len(data) != expected:
        raise ValueError(f"feature segment decodes to {len(data)} bytes, expected {frames} frames of "
                         f"{width}x{height}")
    return np.frombuffer(data, dtype="<u2").reshape(frames, height, width).astype(np.uint16)
