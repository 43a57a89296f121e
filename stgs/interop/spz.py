"""SPZ, Niantic's compressed splat format (nianticlabs/spz), versions 2 and 3 read, version 3 written.

No maintained Python library writes it, so it is written here from the format's published layout. A gzip
stream of a 16-byte little-endian header (magic "NGSP" 0x5053474e, version, count, SH degree, fractional bits,
flags, reserved) and then, attribute by attribute: positions (24-bit signed fixed point, `fractional bits`),
alphas (sigmoid · 255), colours (DC · 0.15 · 255 + 127.5), scales ((log + 10) · 16), rotations (version 2: x y z of
the quaternion with w ≥ 0, 8 bits each; version 3: "smallest three", the largest component's index in 2 bits and
the other three as sign + 9-bit magnitude over 1/√2), and spherical harmonics (coefficient-major, channel inner,
128 + 128·v rounded to buckets: 5 bits for degree 1, 4 above). The stream's axes are right, up, back (the
format's stated frame); ours are OpenCV's right, down, forward, so y and z change sign (a half turn about x).
Flag 0x2 (extensions, from newer writers) is refused with a clear error.
"""

from __future__ import annotations

import gzip
import struct
import zlib

import numpy as np

from stgs.interop.sh import HALF_TURN_X_SIGNS, MAX_DEGREE, coefficients
from stgs.interop.splats import LOGIT_LIMIT, MAX_SPLATS, InteropError, Splats

MAGIC = 0x5053474E
VERSION = 3
HEADER = struct.Struct("<IIIBBBB")
FRACTIONAL_BITS = 12
COLOUR_SCALE = 0.15
SQRT1_2 = np.float32(0.7071067811865476)
FLAG_ANTIALIASED, FLAG_EXTENSIONS = 0x1, 0x2
AXIS_SIGNS = np.array([1.0, -1.0, -1.0], dtype=np.float32)
"""Our axes to the stream's and back (a half turn about x)."""


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def _pack_quats(xyzw: np.ndarray) -> np.ndarray:
    """Version 3's smallest-three rotations, (N, 4) uint8 little-endian words."""
    q = xyzw / np.linalg.norm(xyzw, axis=1, keepdims=True)
    largest = np.abs(q).argmax(1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        skip = largest == i
        neg = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = (np.float32(511) * (np.abs(q[:, i]) / SQRT1_2) + np.float32(0.5)).astype(np.uint32)
        comp = np.where(skip, comp, (comp << 10) | (neg << 9) | np.minimum(mag, 511))
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_quats(data: np.ndarray, version: int) -> np.ndarray:
    """(N, 4) xyzw of version 2's or 3's rotation bytes."""
    if version == 2:
        xyz = data.reshape(-1, 3).astype(np.float32) / np.float32(127.5) - 1
        w = np.sqrt(np.maximum(0, 1 - (xyz * xyz).sum(1)))
        return np.concatenate([xyz, w[:, None]], 1)
    comp = data.reshape(-1, 4).copy().view("<u4")[:, 0]
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((len(comp), 4), dtype=np.float32)
    for i in range(3, -1, -1):
        active = largest != i
        value = SQRT1_2 * (comp & 511).astype(np.float32) / np.float32(511)
        value = np.where((comp >> 9) & 1 == 1, -value, value)
        q[active, i] = value[active]
        comp = np.where(active, comp >> 10, comp)
    rows = np.arange(len(comp))
    q[rows, largest] = np.sqrt(np.maximum(0, 1 - (q * q).sum(1)))
    return q


def encode(splats: Splats) -> bytes:
    splats.check("SPZ")
    n, degree = splats.count, splats.sh_degree
    signs = HALF_TURN_X_SIGNS[:coefficients(degree)].astype(np.float32)
    fixed = np.round(splats.means * AXIS_SIGNS * (1 << FRACTIONAL_BITS)).astype(np.int64)
    reach = (1 << 23) / (1 << FRACTIONAL_BITS)
    if np.abs(fixed).max() >= 1 << 23:
        raise InteropError(f"SPZ: positions must lie within ±{reach:g} of the origin (24-bit fixed point, "
                           f"{FRACTIONAL_BITS} fractional bits)")
    positions = (fixed & 0xFFFFFF).astype("<u4").view(np.uint8).reshape(-1, 4)[:, :3]
    alphas = _u8(255.0 / (1.0 + np.exp(-splats.opacity_logits.astype(np.float64))))
    colours = _u8(splats.sh[:, 0] * np.float32(COLOUR_SCALE * 255.0) + np.float32(0.5 * 255.0))
    scales = _u8((splats.log_scales + np.float32(10.0)) * np.float32(16.0))
    w, xyz = splats.quats[:, :1], splats.quats[:, 1:] * AXIS_SIGNS
    rotations = _pack_quats(np.concatenate([xyz, w], 1))
    rest = splats.sh[:, 1:] * signs[1:, None]
    buckets = np.array([8 if k < 3 else 16 for k in range(rest.shape[1])])[None, :, None]
    q = np.round(rest * np.float32(128.0)).astype(np.int64) + 128
    sh = np.clip((q + buckets // 2) // buckets * buckets, 0, 255).astype(np.uint8)
    header = HEADER.pack(MAGIC, VERSION, n, degree, FRACTIONAL_BITS, 0, 0)
    body = b"".join(a.tobytes() for a in (positions, alphas, colours, scales, rotations, sh))
    return gzip.compress(header + body, compresslevel=9, mtime=0)


def decode(data: bytes, where: str) -> Splats:
    try:
        stream = zlib.decompressobj(16 + zlib.MAX_WBITS)
        head = stream.decompress(data, HEADER.size)
    except zlib.error as exc:
        raise InteropError(f"{where}: not an SPZ file (not gzip: {exc})") from None
    if len(head) < HEADER.size:
        raise InteropError(f"{where}: truncated SPZ header")
    magic, version, n, degree, fractional, flags, _ = HEADER.unpack(head)
    if magic != MAGIC:
        raise InteropError(f"{where}: not an SPZ file (magic {magic:#x})")
    if version not in (2, 3):
        raise InteropError(f"{where}: SPZ version {version} is not supported (2 and 3 are)")
    if not 0 < n <= MAX_SPLATS or degree > MAX_DEGREE or fractional > 23:
        raise InteropError(f"{where}: SPZ header out of range ({n} Gaussians, SH degree {degree}, "
                           f"{fractional} fractional bits)")
    if flags & FLAG_EXTENSIONS:
        raise InteropError(f"{where}: SPZ extensions (flag 0x2) are not supported")
    k = coefficients(degree)
    sizes = (9 * n, n, 3 * n, 3 * n, (4 if version == 3 else 3) * n, 3 * (k - 1) * n)
    try:
        body = stream.decompress(stream.unconsumed_tail, sum(sizes) + 1)
    except zlib.error as exc:
        raise InteropError(f"{where}: corrupt SPZ stream ({exc})") from None
    if len(body) != sum(sizes):
        raise InteropError(f"{where}: SPZ body is {len(body)} bytes, its header asks for {sum(sizes)}")
    parts, at = [], 0
    for size in sizes:
        parts.append(np.frombuffer(body, np.uint8, size, at))
        at += size
    positions, alphas, colours, scales, rotations, sh = parts
    raw = np.zeros((n * 3, 4), dtype=np.uint8)
    raw[:, :3] = positions.reshape(-1, 3)
    fixed = raw.view("<i4")[:, 0]
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = (fixed.astype(np.float32) / np.float32(1 << fractional)).reshape(n, 3) * AXIS_SIGNS
    alpha = np.clip(alphas.astype(np.float64) / 255.0, 0.5 / 255, 1 - 0.5 / 255)
    logits = np.clip(np.log(alpha / (1 - alpha)), -LOGIT_LIMIT, LOGIT_LIMIT).astype(np.float32)
    coeffs = np.empty((n, k, 3), dtype=np.float32)
    coeffs[:, 0] = (colours.reshape(n, 3).astype(np.float32) / np.float32(255) - np.float32(0.5)) / np.float32(
        COLOUR_SCALE)
    signs = HALF_TURN_X_SIGNS[:k].astype(np.float32)
    coeffs[:, 1:] = (sh.reshape(n, k - 1, 3).astype(np.float32) - 128) / np.float32(128) * signs[1:, None]
    xyzw = _unpack_quats(rotations, version)
    quats = np.concatenate([xyzw[:, 3:], xyzw[:, :3] * AXIS_SIGNS], 1)
    log_scales = scales.reshape(n, 3).astype(np.float32) / np.float32(16) - np.float32(10)
    return Splats(means, log_scales, quats, logits, coeffs).check(where)
