"""The static-layer segment: a layered scene's static layer (model format 2), sent once per Period.

The keyframe segment's container (stgs.codec.keyframe: safetensors, lossless
JPEG XL images, checked against the manifest before anything is decoded)
holding the static layer's five canonical attribute images on its own PLAS
grid of side S_s, quantised as a keyframe's (stgs.codec.attributes), and,
for a layer with degree-1 view-dependent colour, three more images:

| name                | dtype   | shape   | content |
|---------------------|---------|---------|---------|
| image.<attribute>   | uint8   | (bytes,)| lossless JPEG XL (attributes.SPECS), S_s x S_s |
| range.<attribute>   | float32 | (2, C)  | [lo, hi] of that image |
| image.sh1_<x,y,z>   | uint8   | (bytes,)| sh_degree 1 only: sh1[:, axis, :] (RGB), 2^16 levels over [min, max] |
| range.sh1_<x,y,z>   | float32 | (2, 3)  | its range |

No temporal features, no deformation field. The header's `__metadata__` has
one key, `streamstgs`: format, version, capacity, grid_side, sh_degree (all
strings).
"""

from __future__ import annotations

import json
import math

import torch
from safetensors.torch import save

from stgs.codec.attributes import SPECS, AttributeSpec, apply_attributes, attribute_range, encode_attributes, quantize
from stgs.codec.keyframe import META_KEY, decode_images, image_shapes, image_tensors, read_container
from stgs.codec.plas import permute_static, plas_order, sort_key
from stgs.codec.plas_config import PLASConfig
from stgs.model.static import StaticLayer

FORMAT = "streamstgs-static"
VERSION = 1
SH1_SPECS = tuple(AttributeSpec(f"sh1_{axis}", "sh1", 3, 1 << 16, None) for axis in "xyz")
"""The view-dependent colour's images: row `axis` of every Gaussian's 3 x 3 sh1 (one RGB image per axis)."""


class StaticSegmentError(ValueError):
    """A static-layer segment that is corrupt or does not match the manifest."""


def static_metadata(capacity: int, sh_degree: int) -> dict[str, str]:
    """The metadata a static-layer segment carries (and a decoder expects)."""
    side = math.isqrt(capacity)
    return {"format": FORMAT, "version": str(VERSION), "capacity": str(capacity), "grid_side": str(side),
            "sh_degree": str(sh_degree)}


def specs_for(sh_degree: int) -> tuple[AttributeSpec, ...]:
    return SPECS + (SH1_SPECS if sh_degree else ())


def sort_static(layer: StaticLayer, cfg: PLASConfig) -> StaticLayer:
    """The layer PLAS-sorted on its S_s x S_s grid (what lets its images compress); the scene is unchanged."""
    return permute_static(layer, plas_order(sort_key(layer, cfg), layer.grid_side, cfg))


def encode_static(layer: StaticLayer) -> bytes:
    """Static-layer segment bytes of a (PLAS-sorted) static layer."""
    side = layer.grid_side
    if side == 0:
        raise ValueError(f"static layer: capacity {layer.capacity} must be a square S_s² to form images")
    images = encode_attributes(layer, side)
    if layer.sh_degree:
        sh1 = layer.sh1.detach().float()
        for axis, spec in enumerate(SH1_SPECS):
            values = sh1[:, axis, :]
            rng = attribute_range(spec, values)
            images[spec.name] = (quantize(spec, values, rng, side), rng)
    meta = static_metadata(layer.capacity, layer.sh_degree)
    return save(image_tensors(images), metadata={META_KEY: json.dumps(meta, sort_keys=True)})


def decode_static(data: bytes, capacity: int, sh_degree: int, max_bytes: int) -> StaticLayer:
    """Parse and check a static-layer segment against the capacity and colour degree the manifest announced."""
    what = "static-layer"
    specs = specs_for(sh_degree)
    tensors = read_container(data, static_metadata(capacity, sh_degree), image_shapes(specs), max_bytes, what,
                             StaticSegmentError)
    side = math.isqrt(capacity)
    values = decode_images(tensors, specs, side, what, StaticSegmentError)
    layer = StaticLayer(capacity, sh_degree)
    apply_attributes(layer, values)
    if sh_degree:
        with torch.no_grad():
            layer.sh1.copy_(torch.stack([values[spec.name] for spec in SH1_SPECS], dim=1))
    return layer


def pack_static(layer: StaticLayer, plas: PLASConfig | None) -> bytes:
    """The static layer sorted (unless `plas` is None) and encoded: the segment the packager writes."""
    return encode_static(layer if plas is None else sort_static(layer, plas))
