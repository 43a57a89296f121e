"""The keyframe segment: everything of a GOP except its temporal features.

Container: a safetensors file (an 8-byte little-endian header length, a JSON
header naming every tensor's dtype, shape and byte range, then raw bytes).
Parsing it executes nothing. Tensors:

| name               | dtype   | shape        | content |
|--------------------|---------|--------------|---------|
| image.<attribute>  | uint8   | (bytes,)     | a lossless JPEG XL file (attributes.SPECS) |
| range.<attribute>  | float32 | (2, C)       | [lo, hi] normalisation range of that image |
| range.features     | float32 | (2, 16)      | per-channel range of the feature video's 12-bit codes |
| field.<name>       | float32 | Linear shape | deformation-field weights (docs/MODEL_FORMAT.md) |

The header's `__metadata__` has one key, `streamstgs`, whose value is a JSON
object (sorted keys) with format, version, gop, grid_side, capacity,
gop_size, window, pe_freqs, feature_bits (all strings). A decoder checks the byte size, the
header, every tensor name and shape and every image's dimensions against what
the manifest announced before decoding anything.

A lossy keyframe (a keyframe rung below the lossless one, KeyframeQuant) has
the same layout with fewer levels in some images, and a metadata key `quant`
naming the bits of each (KeyframeQuant.value). With `field` bits under 32 its
weights are not float32 tensors but, per Linear layer, codes quantised per
output row:

| name                | dtype   | shape    | content |
|---------------------|---------|----------|---------|
| image.field.<name>  | uint8   | (bytes,) | lossless JPEG XL, out x in, one channel, 2^field levels |
| range.field.<name>  | float32 | (2, out) | [lo, hi] of each row |
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, replace

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load, save

from stgs.codec.attributes import SPECS, AttributeSpec, apply_attributes, dequantize, encode_attributes, value_range
from stgs.codec.features import VIDEO_BITS
from stgs.codec.jxl import ImageDecodeError, decode_jxl, encode_jxl
from stgs.codec.quant import FLOAT_FIELD_BITS, LOSSLESS, KeyframeQuant
from stgs.limits import MAX_KEYFRAME_HEADER_BYTES
from stgs.model.gop import FEATURE_DIM, DeformationField, GOPModel, GOPShape

FORMAT = "streamstgs-keyframe"
VERSION = 1
META_KEY = "streamstgs"
"""The one `__metadata__` entry: a JSON object (sorted keys) of the fields below."""


class KeyframeError(ValueError):
    """A keyframe segment that is corrupt or does not match the manifest."""


@dataclass
class Keyframe:
    """A decoded keyframe segment."""

    gop: int
    shape: GOPShape
    attributes: dict[str, torch.Tensor]
    """Dequantised canonical attributes, name -> (N, C)."""
    field: dict[str, torch.Tensor]
    """Deformation-field state dict."""
    feature_ranges: torch.Tensor
    """(2, 16) range of the feature codes."""

    def to_model(self, features: torch.Tensor | None) -> GOPModel:
        """The GOP model with these canonical attributes and the given (E, N, 16) features (used as they
        are, not copied, when already float32 and contiguous); None: a model that holds no features, for a
        GOP whose features stream frame by frame (GOPModel.feature_window)."""
        expected = (self.shape.num_features, self.shape.capacity, FEATURE_DIM)
        if features is not None and features.shape != expected:
            raise ValueError(f"features must be {expected}, got {tuple(features.shape)}")
        # Without features: they alone are E·N·16 floats (260 MB at N = 65,536), and filling them first cost
        # the player's pre-decode time. (Not torch's meta device: its first use costs half a second.)
        model = GOPModel(self.shape, features=False)
        model.field.load_state_dict(self.field)
        apply_attributes(model, self.attributes)
        if features is not None:
            model.features.data = features.to(torch.float32).contiguous()
        return model


def quant_specs(quant: KeyframeQuant) -> tuple[AttributeSpec, ...]:
    """attributes.SPECS at the levels of `quant`."""
    return tuple(replace(spec, levels=1 << getattr(quant, spec.name)) for spec in SPECS)


def keyframe_metadata(gop: int, shape: GOPShape, quant: KeyframeQuant = LOSSLESS) -> dict[str, str]:
    """The metadata a keyframe segment of GOP `gop` carries (and a decoder expects)."""
    meta = {"format": FORMAT, "version": str(VERSION), "gop": str(gop), "grid_side": str(shape.grid_side),
            "capacity": str(shape.capacity), "gop_size": str(shape.gop_size), "window": str(shape.window),
            "pe_freqs": str(shape.pe_freqs), "feature_bits": str(VIDEO_BITS)}
    if not quant.lossless:
        meta["quant"] = quant.value
    return meta


def quantize_weight(weight: torch.Tensor, bits: int) -> tuple[np.ndarray, torch.Tensor]:
    """(out, in) weights -> (out, in, 1) uint8 codes at 2^bits levels over each row's [lo, hi], and that (2, out)
    range."""
    w = weight.detach().float()
    rng = value_range(w.T)  # a column per output row
    lo, hi = rng
    levels = (1 << bits) - 1
    codes = torch.round((w - lo[:, None]) / (hi - lo)[:, None] * levels).clamp(0, levels)
    return codes.to(torch.uint8).numpy()[:, :, None], rng.contiguous()


def dequantize_weight(codes: np.ndarray, rng: torch.Tensor, bits: int) -> torch.Tensor:
    """quantize_weight's codes back to (out, in) float32 weights."""
    levels = (1 << bits) - 1
    if int(codes.max(initial=0)) > levels:
        raise ValueError(f"code {int(codes.max())} exceeds {levels}")
    unit = torch.from_numpy(codes[:, :, 0].astype(np.float32)) / levels
    return unit * (rng[1] - rng[0])[:, None] + rng[0][:, None]


def encode_keyframe(gop: int, model: GOPModel, feature_ranges: torch.Tensor, quant: KeyframeQuant = LOSSLESS) -> bytes:
    """Keyframe segment bytes of a PLAS-sorted GOP model, its images and weights at `quant`."""
    side = model.shape.grid_side
    if side == 0:
        raise ValueError("the capacity must be a square S² to form attribute images")
    tensors = image_tensors(encode_attributes(model, side, quant_specs(quant)))
    tensors["range.features"] = feature_ranges.float().contiguous()
    for name, weight in model.field.state_dict().items():
        if quant.field == FLOAT_FIELD_BITS:
            tensors[f"field.{name}"] = weight.detach().float().contiguous()
        else:
            codes, rng = quantize_weight(weight, quant.field)
            tensors |= image_tensors({f"field.{name}": (codes, rng)})
    meta = keyframe_metadata(gop, model.shape, quant)
    # One metadata key: safetensors writes several in hash order, which would break byte-identical re-packs.
    return save(tensors, metadata={META_KEY: json.dumps(meta, sort_keys=True)})


def _header(data: bytes, what: str, error: type[ValueError]) -> dict:
    if len(data) < 8:
        raise error(f"{what} segment is truncated")
    size = struct.unpack_from("<Q", data)[0]
    if size > MAX_KEYFRAME_HEADER_BYTES or 8 + size > len(data):
        raise error(f"{what} header claims {size} bytes")
    try:
        header = json.loads(data[8:8 + size])
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{what} header is not JSON ({exc})") from exc
    if not isinstance(header, dict):
        raise error(f"{what} header is not a JSON object")
    return header


def read_container(data: bytes, metadata: dict[str, str], want: dict[str, tuple[int, ...] | None], max_bytes: int,
                   what: str, error: type[ValueError]) -> dict[str, torch.Tensor]:
    """The tensors of a segment in this container (`what`: "keyframe" or "static-layer"), refused with `error`
    unless its size, metadata, tensor names, dtypes and shapes are what the manifest announced (`want`: name ->
    shape, None for a JPEG XL byte string) and every float is finite; checked before anything is decoded."""
    if len(data) > max_bytes:
        raise error(f"{what} segment is {len(data)} bytes, over the {max_bytes}-byte limit")
    header = _header(data, what, error)
    try:
        meta = json.loads((header.get("__metadata__") or {}).get(META_KEY, "{}"))
    except (json.JSONDecodeError, TypeError, AttributeError) as exc:
        raise error(f"{what} metadata is not JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise error(f"{what} metadata is not a JSON object")
    for key, value in metadata.items():
        if meta.get(key) != value:
            raise error(f"{what} {key} is {meta.get(key)!r}, expected {value!r}")
    if set(meta) - set(metadata):
        raise error(f"{what} metadata has unexpected keys {sorted(set(meta) - set(metadata))}")
    names = set(header) - {"__metadata__"}
    if names != set(want):
        raise error(f"{what} tensors differ from the format (missing {sorted(set(want) - names)}, "
                    f"unknown {sorted(names - set(want))})")
    for name, shp in want.items():
        entry = header[name]
        dtype = "U8" if shp is None else "F32"
        if not isinstance(entry, dict) or entry.get("dtype") != dtype:
            raise error(f"{what} tensor {name} must be {dtype}")
        if shp is not None and (not isinstance(entry.get("shape"), list) or tuple(entry["shape"]) != shp):
            raise error(f"{what} tensor {name} has shape {entry.get('shape')}, expected {list(shp)}")
    try:
        tensors = load(data)
    except (SafetensorError, ValueError) as exc:
        raise error(f"{what} segment is corrupt ({exc})") from exc
    for name, t in tensors.items():
        if t.dtype == torch.float32 and not torch.isfinite(t).all():
            raise error(f"{what} tensor {name} contains NaN or Inf")
    return tensors


def decode_images(tensors: dict[str, torch.Tensor], specs: tuple[AttributeSpec, ...], side: int, what: str,
                  error: type[ValueError]) -> dict[str, torch.Tensor]:
    """name -> dequantised (S², C) values of each spec's JPEG XL image and range."""
    attributes = {}
    for spec in specs:
        try:
            codes = decode_jxl(tensors[f"image.{spec.name}"].numpy().tobytes(), (side, side, spec.channels),
                               spec.dtype)
            attributes[spec.name] = dequantize(spec, np.asarray(codes), tensors[f"range.{spec.name}"])
        except (ImageDecodeError, ValueError) as exc:
            raise error(f"{what} image {spec.name}: {exc}") from exc
    return attributes


def image_tensors(images: dict[str, tuple[np.ndarray, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The container's image.<name> (lossless JPEG XL bytes) and range.<name> tensors of quantised images."""
    tensors: dict[str, torch.Tensor] = {}
    for name, (codes, rng) in images.items():
        tensors[f"image.{name}"] = torch.frombuffer(bytearray(encode_jxl(codes)), dtype=torch.uint8)
        tensors[f"range.{name}"] = rng.contiguous()
    return tensors


def image_shapes(specs: tuple[AttributeSpec, ...]) -> dict[str, tuple[int, ...] | None]:
    """name -> shape of the image and range tensors of `specs` (None: a JPEG XL byte string)."""
    want: dict[str, tuple[int, ...] | None] = {}
    for spec in specs:
        want[f"image.{spec.name}"] = None
        want[f"range.{spec.name}"] = (2, spec.channels)
    return want


def field_shapes(shape: GOPShape) -> dict[str, tuple[int, ...]]:
    """Deformation-field weight name -> (out, in)."""
    field = DeformationField(shape.window, shape.pe_freqs)
    return {k: tuple(v.shape) for k, v in field.state_dict().items()}


def expected_tensors(shape: GOPShape, quant: KeyframeQuant = LOSSLESS) -> dict[str, tuple[int, ...] | None]:
    """name -> shape (None for the variable-length JPEG XL byte strings)."""
    want = image_shapes(SPECS)
    want["range.features"] = (2, FEATURE_DIM)
    for name, weight in field_shapes(shape).items():
        if quant.field == FLOAT_FIELD_BITS:
            want[f"field.{name}"] = weight
        else:
            want[f"image.field.{name}"] = None
            want[f"range.field.{name}"] = (2, weight[0])
    return want


@dataclass
class KeyframeSegment:
    """A keyframe segment parsed and checked against the manifest; its images are not decoded yet (a player
    starts the feature video, which needs only the feature ranges, while they decode)."""

    gop: int
    shape: GOPShape
    tensors: dict[str, torch.Tensor]
    quant: KeyframeQuant = LOSSLESS

    @property
    def feature_ranges(self) -> torch.Tensor:
        """(2, 16) range of the feature codes."""
        return self.tensors["range.features"]

    def decode(self) -> Keyframe:
        """Decode the JPEG XL images (KeyframeError when one does not decode or is not the announced size)."""
        attributes = decode_images(self.tensors, quant_specs(self.quant), self.shape.grid_side, "keyframe",
                                   KeyframeError)
        if self.quant.field == FLOAT_FIELD_BITS:
            field = {k[len("field."):]: v for k, v in self.tensors.items() if k.startswith("field.")}
        else:
            field = {}
            for name, (out, inp) in field_shapes(self.shape).items():
                try:
                    codes = decode_jxl(self.tensors[f"image.field.{name}"].numpy().tobytes(), (out, inp, 1),
                                       np.dtype(np.uint8))
                    field[name] = dequantize_weight(np.asarray(codes), self.tensors[f"range.field.{name}"],
                                                    self.quant.field)
                except (ImageDecodeError, ValueError) as exc:
                    raise KeyframeError(f"keyframe image field.{name}: {exc}") from exc
        return Keyframe(self.gop, self.shape, attributes, field, self.feature_ranges)


def parse_keyframe(data: bytes, shape: GOPShape, gop: int, max_bytes: int,
                   quant: KeyframeQuant = LOSSLESS) -> KeyframeSegment:
    """Parse and check a keyframe segment against the shape, GOP index and quantisation the manifest announced."""
    tensors = read_container(data, keyframe_metadata(gop, shape, quant), expected_tensors(shape, quant), max_bytes,
                             "keyframe", KeyframeError)
    return KeyframeSegment(gop, shape, tensors, quant)


def decode_keyframe(data: bytes, shape: GOPShape, gop: int, max_bytes: int,
                    quant: KeyframeQuant = LOSSLESS) -> Keyframe:
    """parse_keyframe, then its images decoded."""
    return parse_keyframe(data, shape, gop, max_bytes, quant).decode()
