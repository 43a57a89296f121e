"""Lossless JPEG XL images through OpenImageIO, with sizes checked before decoding."""

from __future__ import annotations

import os
import struct
import tempfile

import numpy as np
import OpenImageIO as oiio

_FORMATS = {np.dtype(np.uint8): oiio.UINT8, np.dtype(np.uint16): oiio.UINT16}


class ImageDecodeError(ValueError):
    """A JPEG XL payload that is corrupt or not the size the manifest promised."""


def encode_jxl(pixels: np.ndarray) -> bytes:
    """(H, W, C) uint8/uint16 -> lossless JPEG XL bytes (OpenImageIO's default for JXL is lossless)."""
    if pixels.ndim != 3 or pixels.dtype not in _FORMATS:
        raise ValueError("encode_jxl takes an (H, W, C) uint8 or uint16 array")
    h, w, c = pixels.shape
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "image.jxl")
        out = oiio.ImageOutput.create(path)
        if out is None or not out.open(path, oiio.ImageSpec(w, h, c, _FORMATS[pixels.dtype])):
            raise RuntimeError(f"OpenImageIO cannot write JPEG XL: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise RuntimeError(f"OpenImageIO failed writing JPEG XL: {oiio.geterror()}")
        with open(path, "rb") as f:
            return pad_small(f.read())


MIN_FILE_BYTES = 256
"""OpenImageIO's JPEG XL reader rejects files shorter than about 128 bytes (tiny or flat images)."""


def pad_small(data: bytes) -> bytes:
    """Append an ignorable 'skip' box to a JPEG XL container shorter than MIN_FILE_BYTES.

    The container is ISO BMFF boxes; decoders skip box types they do not know,
    so the image is unchanged.
    """
    if len(data) >= MIN_FILE_BYTES or not data.startswith(b"\x00\x00\x00\x0cJXL "):
        return data
    pad = max(0, MIN_FILE_BYTES - len(data) - 8)  # a skip box is at least its 8-byte header
    return data + struct.pack(">I4s", 8 + pad, b"skip") + bytes(pad)


def decode_jxl(data: bytes, shape: tuple[int, int, int], dtype: np.dtype) -> np.ndarray:
    """JPEG XL bytes -> (H, W, C) array; the header must announce exactly `shape` before any pixel is read."""
    dtype = np.dtype(dtype)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "image.jxl")
        with open(path, "wb") as f:
            f.write(data)
        inp = oiio.ImageInput.open(path)
        if inp is None:
            raise ImageDecodeError(f"not a readable JPEG XL image ({oiio.geterror().strip()})")
        try:
            spec = inp.spec()
            got = (spec.height, spec.width, spec.nchannels)
            if got != tuple(shape):
                raise ImageDecodeError(f"image is {got[1]}x{got[0]}x{got[2]}, expected "
                                       f"{shape[1]}x{shape[0]}x{shape[2]}")
            pixels = inp.read_image(format=_FORMATS[dtype])
        finally:
            inp.close()
    if pixels is None:
        raise ImageDecodeError(f"JPEG XL pixel data is corrupt ({oiio.geterror().strip()})")
    return np.asarray(pixels, dtype=dtype).reshape(shape)
