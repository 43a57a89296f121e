"""The AV1 10-bit feature video: what browsers decode (WebCodecs), beside the 12-bit HEVC ladder.

SVT-AV1 (in PyAV's wheel) encodes 4:2:0 10-bit only, so a 10-bit feature frame travels as the luma plane of
a yuv420p10le picture whose two chroma planes hold the neutral value 512: a constant plane costs a few
bytes per frame and no decoder reads it back. The sequence is main profile, 10-bit, 4:2:0, limited range
left unsignalled (decoders hand the plane's codes through unchanged: nothing here converts colour).

The settings (docs/PACKAGING.md, "The browser ladder", has the measurements): a constant QP with adaptive
quantisation off (the ladder point, as for HEVC: it renders better than SVT-AV1's default CRF at equal
bytes), temporal filtering off (a denoiser of the key frame, made for pictures, which costs rendered quality at
equal bytes), preset 8 (a slower preset took longer and rendered lower). Each GOP's segment decodes alone and a
re-encode is byte-identical: one key frame at the start with keyint = E and scene-change detection off, level of
parallelism 1 (one thread per encode; the packager runs encodes side by side), bit-exact muxing. SVT-AV1's own
log lines (its version banner per encoder) are silenced through its SVT_LOG variable unless the caller set it.
"""

from __future__ import annotations

import os

import av
import numpy as np

from stgs.codec import FEATURE_CODECS
from stgs.codec.mp4 import MP4Error, sample_entry_config

BITS = FEATURE_CODECS["av1"][1]
PIXEL_FORMAT = "yuv420p10le"
"""The pictures SVT-AV1 encodes and dav1d returns: the feature frame is their luma plane."""
NEUTRAL = 1 << (BITS - 1)
"""The chroma planes' constant value."""
PRESETS = tuple(str(p) for p in range(14))
"""SVT-AV1 presets, slowest (0) to fastest (13)."""
QUANTIZERS = range(1, 64)
"""SVT-AV1 QPs (the ladder points of the AV1 set)."""
CODEC_TAG = "av01"


def svt_params(qp: int, keyint: int) -> str:
    """SVT-AV1 settings for one GOP's segment (see the module docstring)."""
    return f"qp={qp}:aq-mode=0:enable-tf=0:keyint={keyint}:scd=0:lp=1"


def quiet_svt() -> None:
    """Keep SVT-AV1's banner off stderr (errors still print) unless SVT_LOG is set already."""
    os.environ.setdefault("SVT_LOG", "1")


def to_picture(plane: np.ndarray) -> av.VideoFrame:
    """An (H, W) uint16 10-bit feature frame as a yuv420p10le picture: the luma plane, neutral chroma."""
    h, w = plane.shape
    frame = av.VideoFrame(w, h, PIXEL_FORMAT)
    for i, p in enumerate(frame.planes):
        rows = h if i == 0 else h // 2
        cols = w if i == 0 else w // 2
        view = np.frombuffer(memoryview(p), np.uint16).reshape(-1, p.line_size // 2)[:rows, :cols]
        view[...] = plane if i == 0 else NEUTRAL
    return frame


def luma(frame: av.VideoFrame) -> np.ndarray:
    """The (H, W) uint16 luma plane of a decoded yuv420p10le picture (a copy: the decoder reuses its buffers)."""
    p = frame.planes[0]
    return np.frombuffer(memoryview(p), np.uint16).reshape(-1, p.line_size // 2)[:frame.height, :frame.width].copy()


def av1_codecs(init: bytes) -> str:
    """RFC 6381 codecs string (AV1-ISOBMFF §5, e.g. 'av01.0.04M.10') from an init segment's av1C box.

    The optional fields (monochrome, chroma subsampling, colour) are written only when the stream departs from
    their defaults (4:2:0, not monochrome); the colour fields then take the defaults, as this packager never
    signals colour."""
    _, b = sample_entry_config(init, (CODEC_TAG,), "av1C", "AV1")
    if len(b) < 4 or b[0] != 0x81:
        raise MP4Error("av1C box is truncated or not version 1")
    profile, level = b[1] >> 5, b[1] & 0x1F
    tier = "H" if b[2] & 0x80 else "M"
    high, twelve, mono = (b[2] >> 6) & 1, (b[2] >> 5) & 1, (b[2] >> 4) & 1
    sub_x, sub_y, position = (b[2] >> 3) & 1, (b[2] >> 2) & 1, b[2] & 3
    depth = 12 if twelve else 10 if high else 8
    codecs = f"av01.{profile}.{level:02d}{tier}.{depth:02d}"
    if mono or (sub_x, sub_y, position) != (1, 1, 0):
        codecs += f".{mono}.{sub_x}{sub_y}{position}.01.01.01.0"
    return codecs
