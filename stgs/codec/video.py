"""Feature video, encoded and decoded in-process with PyAV, one closed GOP per segment, in one of two codecs
(`FeatureCodec`): 12-bit gray HEVC (libx265), the reference ladder, and 10-bit AV1 (SVT-AV1, decoded by
dav1d; stgs.codec.av1), the ladder browsers decode.

HEVC encoding settings (constant QP, closed GOP, IDR at the first frame, no scene
cuts, keyint = E, one x265 thread, bit-exact muxing) make each GOP's segment
decodable alone after the init segment, and make a re-encode of the same
frames produce the same bytes (AV1's: stgs.codec.av1). Decoding yields one
frame at a time and refuses, before decoding a single picture, a stream whose
codec or size is not the one announced, and a picture of another pixel
format; libavcodec's own `max_pixels` bounds what an in-band parameter set
can make it allocate.

Why PyAV and not the ffmpeg binary through a pipe: the binary costs a process
start before the first frame and a pipe copy per frame (bench/packaging/video_io.py
measures both; docs/BENCHMARKS.md, "Video I/O"). The binary's one advantage, that
a decoder crash takes down only a child, is weighed in docs/CLIENT.md.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction

import av
import numpy as np

from stgs.codec import FEATURE_CODECS, av1
from stgs.codec.mp4 import hevc_codecs
from stgs.errors import StgsError
from stgs.memory import filled_heap
from stgs.tree import rep_id

PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow")
"""x265 presets, fastest first."""
DEFAULT_QPS = (16, 20, 24, 28, 32)
"""The HEVC feature-video QP ladder `stgs pack` encodes unless told otherwise (one Representation per QP)."""
PIXEL_FORMAT = "gray12le"
"""The HEVC feature video's pixels: one 12-bit channel, stored little-endian in 16 bits."""
CODEC_TAG = "hvc1"
"""Parameter sets in the init segment's sample description only (what MSE and the DASH profile expect)."""
AV1_LADDER = (12, 19, 27, 35, 43)
"""The AV1 set's QP ladder: one point beside each default HEVC QP, at about its bytes (docs/PACKAGING.md)."""
LADDERS = ("auto", "fixed")
"""How a pack uses a codec's points (stgs pack --ladder): auto picks the rungs from its candidates by measured quality;
fixed keeps every point of its ladder."""
HEVC_CANDIDATES = (12, 16, 20, 24, 28, 32, 36, 40)
"""The HEVC QPs the auto ladder measures and picks its rungs from (docs/PACKAGING.md, "The auto ladder")."""
AV1_CANDIDATES = (10, 16, 22, 28, 34, 40, 46, 52)
"""The AV1 QPs the auto ladder measures and picks its rungs from: about the span of the HEVC candidates' bytes."""


@dataclass(frozen=True)
class FeatureCodec:
    """One feature-video codec of the tree: how its frames are coded, named and checked."""

    name: str
    """`hevc` or `av1` (the --codecs names)."""
    bits: int
    """Bit depth of the feature codes its frames carry (manifests/PROFILE.md, "Feature frames")."""
    encoder: str
    """The libav encoder."""
    pixel_format: str
    """The pictures it encodes and its decoder returns."""
    codec_tag: str
    """The MP4 sample entry."""
    presets: tuple[str, ...]
    default_preset: str
    quantizers: range
    """Valid ladder points (the QP of x265 or of SVT-AV1)."""
    ladder: tuple[int, ...]
    """The ladder points of a fixed ladder unless told otherwise."""
    candidates: tuple[int, ...]
    """The ladder points the auto ladder measures unless told otherwise."""

    def rep_id(self, q: int) -> str:
        """The Representation id of ladder point `q` (stgs.tree.rep_id)."""
        return rep_id(q, self.name)

    def codecs(self, init: bytes) -> str:
        """The RFC 6381 @codecs string of an init segment of this codec."""
        return hevc_codecs(init) if self.name == "hevc" else av1.av1_codecs(init)

    def picture(self, plane: np.ndarray) -> av.VideoFrame:
        """An (H, W) uint16 feature frame as the picture the encoder takes."""
        if self.name == "hevc":
            return av.VideoFrame.from_ndarray(plane, format=PIXEL_FORMAT)
        return av1.to_picture(plane)

    def plane(self, frame: av.VideoFrame) -> np.ndarray:
        """The (H, W) uint16 feature frame of a decoded picture."""
        return frame.to_ndarray() if self.name == "hevc" else av1.luma(frame)


HEVC = FeatureCodec("hevc", FEATURE_CODECS["hevc"][1], "libx265", PIXEL_FORMAT, CODEC_TAG, PRESETS, "medium",
                    range(0, 52), DEFAULT_QPS, HEVC_CANDIDATES)
AV1 = FeatureCodec("av1", FEATURE_CODECS["av1"][1], "libsvtav1", av1.PIXEL_FORMAT, av1.CODEC_TAG, av1.PRESETS, "8",
                   av1.QUANTIZERS, AV1_LADDER, AV1_CANDIDATES)
CODECS = {c.name: c for c in (HEVC, AV1)}
"""Every feature codec by name, the reference (HEVC) first (stgs.codec.FEATURE_CODECS names them)."""


class VideoError(ValueError):
    """A feature segment that does not decode to the frames announced."""


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
        if rate <= 0:
            raise ValueError(f"no video timing for {num_features} features per {gop_size} frames at {fps} fps")
        scale = 1
        while rate.numerator * scale < 1000:  # a timescale of at least 1 kHz
            scale *= 2
        return cls(rate, rate.numerator * scale, rate.denominator * scale)

    def segment_ticks(self, num_features: int) -> int:
        return num_features * self.frame_ticks


def x265_params(qp: int, keyint: int, crf: bool = False, loop_filters: bool = True) -> str:
    """x265 settings; crf=True uses the value as a CRF instead of a constant QP (benchmarks only);
    loop_filters=False turns the in-loop deblocking and SAO filters off (the stream says so, and the decoder
    skips them)."""
    params = [f"{'crf' if crf else 'qp'}={qp}", f"keyint={keyint}", f"min-keyint={keyint}", "scenecut=0",
              "open-gop=0", "info=0", "pools=1", "frame-threads=1", "lookahead-threads=0", "log-level=error"]
    if not loop_filters:
        params += ["no-deblock=1", "no-sao=1"]  # "deblock=0" would read as a deblocking offset, not "off"
    return ":".join(params)


def encode_gop(frames: np.ndarray, qp: int, timing: VideoTiming, preset: str | None = None,
               crf: bool = False, loop_filters: bool = True, codec: FeatureCodec = HEVC) -> bytes:
    """(E, H, W) uint16 frames of `codec.bits` -> a single-fragment fragmented MP4 of `codec` (preset None: the
    codec's default); for HEVC see x265_params for crf and loop_filters (AV1 is always a constant QP with its
    in-loop filters)."""
    if frames.ndim != 3 or frames.dtype != np.uint16:
        raise ValueError("encode_gop takes (E, H, W) uint16 frames")
    preset = codec.default_preset if preset is None else preset
    if preset not in codec.presets:
        raise StgsError(f"unknown {codec.name} preset {preset!r}; choose from {', '.join(codec.presets)}")
    if qp not in codec.quantizers:
        raise StgsError(f"{codec.name} ladder point {qp} is outside {codec.quantizers.start}.."
                        f"{codec.quantizers.stop - 1}")
    if codec.name == "hevc":
        options = {"preset": preset, "x265-params": x265_params(qp, frames.shape[0], crf, loop_filters)}
    else:
        av1.quiet_svt()
        options = {"preset": preset, "svtav1-params": av1.svt_params(qp, frames.shape[0])}
    with filled_heap:  # libx265 reads memory it never wrote: see stgs.memory.FilledHeap
        return _encode(frames, timing, codec, options | {"flags": "+bitexact"})


def _encode(frames: np.ndarray, timing: VideoTiming, codec: FeatureCodec, options: dict[str, str]) -> bytes:
    e, h, w = frames.shape
    out = io.BytesIO()
    muxer = {"movflags": "+frag_keyframe+empty_moov+default_base_moof", "fflags": "+bitexact",
             "video_track_timescale": str(timing.timescale), "frag_duration": "2000000000"}
    try:
        with av.open(out, "w", format="mp4", options=muxer) as container:
            stream = container.add_stream(codec.encoder, rate=timing.rate, options=options)
            assert isinstance(stream, av.VideoStream)  # a video encoder's
            stream.width, stream.height, stream.pix_fmt = w, h, codec.pixel_format
            stream.codec_tag = codec.codec_tag
            stream.codec_context.thread_count = 1
            stream.time_base = 1 / timing.rate
            packets: list[av.Packet] = []
            for i, plane in enumerate(np.ascontiguousarray(frames)):
                frame = codec.picture(plane)
                frame.pts, frame.time_base = i, 1 / timing.rate
                packets += stream.encode(frame)
            packets += stream.encode(None)
            container.mux(_decode_timestamps(packets, e))
    except av.FFmpegError as exc:
        raise RuntimeError(f"feature video encode failed: {exc}") from exc
    return out.getvalue()


def _decode_timestamps(packets: list[av.Packet], count: int) -> list[av.Packet]:
    """Packets in decode order with their decode timestamps and durations set from their presentation timestamps.

    libx265 in PyAV's FFmpeg build sometimes returns garbage decode timestamps (seen as -2.8e17 from the second
    encoder of a process on); the presentation timestamps are the frame numbers we gave. The i-th decoded packet
    gets the i-th smallest pts, less the reorder delay that keeps every dts at or before its pts."""
    pts = [-1 if p.pts is None else p.pts for p in packets]
    if sorted(pts) != list(range(count)):
        raise RuntimeError(f"the encoder returned presentation timestamps {pts}, expected 0..{count - 1}")
    delay = max(0, max(rank - p for rank, p in enumerate(pts)))
    for rank, packet in enumerate(packets):
        packet.dts, packet.duration = rank - delay, 1
    return packets


def _coded_pixels(width: int, height: int) -> int:
    """Pixels of the largest picture HEVC codes for a width x height frame (sides padded to whole 64-pixel CTUs)."""
    return -(-width // 64) * 64 * (-(-height // 64) * 64)


_DECODERS = {"hevc": ("hevc",), "av1": ("libdav1d", "av1")}
"""The libav decoders that may read each codec's segments."""


def iter_frames(data: bytes, frames: int, height: int, width: int, threads: int = 0,
                codec: FeatureCodec = HEVC) -> Iterator[np.ndarray]:
    """The frames of the feature video `data` (init + media segment), (H, W) uint16 each, decoded one at a time
    with `threads` decoder threads (0: libavcodec's choice). Raises VideoError for a video that does not decode,
    is not `codec` at `width`x`height` in its pixel format (hence bit depth), or holds a number of frames other
    than `frames` (a frame past those is never converted)."""
    count = 0
    try:
        with av.open(io.BytesIO(data), "r", format="mp4") as container:
            if len(container.streams.video) != 1:
                raise VideoError(f"feature segment holds {len(container.streams.video)} video streams, expected 1")
            stream = container.streams.video[0]
            ctx = stream.codec_context
            if ctx.name not in _DECODERS[codec.name]:
                raise VideoError(f"feature segment is {ctx.name}, expected {codec.name}")
            if (ctx.width, ctx.height) != (width, height):
                raise VideoError(f"feature segment is {ctx.width}x{ctx.height}, expected {width}x{height}")
            ctx.options = {"max_pixels": str(_coded_pixels(width, height))}
            ctx.thread_count = threads
            ctx.thread_type = "AUTO"
            for frame in container.decode(stream):
                if (frame.width, frame.height, frame.format.name) != (width, height, codec.pixel_format):
                    raise VideoError(f"feature frame {count} is {frame.width}x{frame.height} {frame.format.name}, "
                                     f"expected {width}x{height} {codec.pixel_format} ({codec.bits}-bit "
                                     f"{codec.name})")
                if count == frames:
                    raise VideoError(f"feature segment holds more than the {frames} frames of {width}x{height} "
                                     "announced")
                count += 1
                yield codec.plane(frame)
    except av.FFmpegError as exc:
        raise VideoError(f"feature segment does not decode: {exc.strerror or exc}") from None
    if count != frames:
        raise VideoError(f"feature segment decodes to {count} frames, expected {frames} of {width}x{height}")


def decode_segment(init: bytes, media: bytes, frames: int, height: int, width: int, threads: int = 0,
                   codec: FeatureCodec = HEVC) -> np.ndarray:
    """init + one media segment -> (frames, H, W) uint16, decoded frame by frame into one array (see iter_frames
    for what is refused)."""
    out = np.empty((frames, height, width), np.uint16)
    for i, frame in enumerate(iter_frames(init + media, frames, height, width, threads, codec)):
        out[i] = frame  # iter_frames stops before a frame past `frames`
    return out
