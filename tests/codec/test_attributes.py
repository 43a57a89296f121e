"""Attribute images: the clip ranges and levels of docs/ARCHITECTURE.md, bit-exact through lossless JPEG XL."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch

from stgs.codec.attributes import SPECS, dequantize, encode_attributes
from stgs.codec.jxl import ImageDecodeError, decode_jxl, encode_jxl
from tests.model.test_gop import random_model


def test_specs_follow_the_design():
    specs = {s.name: s for s in SPECS}
    assert specs["rotation"].clip == (-1.0, 2.0) and specs["rotation"].levels == 128
    assert specs["opacity"].clip == (-4.0, 4.0) and specs["opacity"].levels == 64
    assert specs["color"].clip == (0.0, 4.0)
    assert specs["scale"].levels == 64
    assert specs["position"].levels == 65536 and specs["position"].dtype == np.uint16


def test_jxl_round_trip_is_bit_exact():
    model = random_model(n=24 * 24, gop_size=3)
    for name, (codes, _) in encode_attributes(model, 24).items():
        back = decode_jxl(encode_jxl(codes), codes.shape, codes.dtype)
        assert back.dtype == codes.dtype and np.array_equal(back, codes), name
        spec = next(s for s in SPECS if s.name == name)
        assert int(codes.max()) < spec.levels


@pytest.mark.parametrize("missing", [1, 4, 7, 8, 9, 100])
def test_small_files_are_padded_to_the_minimum_whatever_their_size(missing):
    from stgs.codec.jxl import MIN_FILE_BYTES, pad_small

    container = b"\x00\x00\x00\x0cJXL \r\n\x87\n"
    data = container + b"\x00" * (MIN_FILE_BYTES - missing - len(container))
    padded = pad_small(data)
    assert padded.startswith(data) and len(padded) >= MIN_FILE_BYTES
    size, kind = struct.unpack(">I4s", padded[len(data):len(data) + 8])
    assert kind == b"skip" and size == len(padded) - len(data)  # one well-formed box to the end


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_dequantised_error_is_at_most_half_a_step(spec):
    model = random_model(n=16 * 16, gop_size=3)
    codes, rng = encode_attributes(model, 16)[spec.name]
    values = getattr(model, spec.param).detach().reshape(256, spec.channels)
    clipped = values.clamp(rng[0], rng[1])
    step = (rng[1] - rng[0]) / (spec.levels - 1)
    err = (dequantize(spec, codes, rng) - clipped).abs()
    assert (err <= step / 2 + 1e-6).all()


def test_decoder_checks_dimensions_before_reading():
    data = encode_jxl(np.zeros((8, 8, 3), dtype=np.uint8))
    with pytest.raises(ImageDecodeError, match="expected"):
        decode_jxl(data, (16, 16, 3), np.uint8)
    with pytest.raises(ImageDecodeError):
        decode_jxl(b"not an image at all", (8, 8, 3), np.uint8)


def test_features_tiling_is_invertible():
    from stgs.codec.features import tile_frames, untile_frames

    codes = torch.arange(2 * 9 * 16).reshape(2, 9, 16)
    frames = tile_frames(codes, 3)
    assert frames.shape == (2, 12, 12)
    assert frames[0, 0, 3] == codes[0, 0, 1]  # channel 1: tile row 0, tile column 1
    assert frames[0, 3, 0] == codes[0, 0, 4]  # channel 4: tile row 1, tile column 0
    assert torch.equal(untile_frames(frames, 3), codes)
