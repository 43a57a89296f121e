"""glTF 2.0 binary (.glb) with the ratified KHR_gaussian_splatting extension, written and read with pygltflib.

One mesh of one primitive, mode POINTS, whose attributes are the Gaussians: POSITION (float VEC3, with its
bounds), KHR_gaussian_splatting:ROTATION (float VEC4, xyzw, unit), :SCALE (float VEC3, linear), :OPACITY (float
SCALAR, after the sigmoid), :SH_DEGREE_0_COEF_0 and :SH_DEGREE_l_COEF_n (float VEC3, the coefficients as a 3DGS
PLY stores them), and the extension object {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}. The
linear scales and opacities are read back to logs and logits by canonical preimage (stgs.interop.splats), so a
file read and written again has the same bytes.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pygltflib as gl

from stgs.interop.sh import coefficients, degree_of
from stgs.interop.splats import (
    MAX_SPLATS,
    InteropError,
    Splats,
    exp32,
    log_scales_of,
    logits_of,
    sigmoid32,
    unit_quats,
)

EXTENSION = "KHR_gaussian_splatting"
PREFIX = f"{EXTENSION}:"
MAX_JSON_BYTES = 1 << 22
"""Largest JSON chunk read."""
TYPES = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


def sh_attribute(k: int) -> str:
    """The attribute of coefficient k (flat, DC first) of the extension."""
    degree = int(np.sqrt(k))
    return f"{PREFIX}SH_DEGREE_{degree}_COEF_{k - degree * degree}"


def _activated(splats: Splats) -> dict[str, np.ndarray]:
    opacity, scale = sigmoid32(splats.opacity_logits), exp32(splats.log_scales)
    xyzw = unit_quats(splats.quats)[:, [1, 2, 3, 0]]
    out = {"POSITION": splats.means, f"{PREFIX}ROTATION": xyzw, f"{PREFIX}SCALE": scale, f"{PREFIX}OPACITY": opacity}
    for k in range(splats.sh.shape[1]):
        out[sh_attribute(k)] = splats.sh[:, k]
    return out


def encode(splats: Splats) -> bytes:
    splats.check("glb")
    arrays = _activated(splats)
    blob, views, accessors, attributes = bytearray(), [], [], {}
    for name, array in arrays.items():
        array = np.ascontiguousarray(array, dtype="<f4")
        kind = "SCALAR" if array.ndim == 1 else f"VEC{array.shape[1]}"
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=array.nbytes, target=gl.ARRAY_BUFFER))
        bounds = {"min": array.min(0).tolist(), "max": array.max(0).tolist()} if name == "POSITION" else {}
        accessors.append(gl.Accessor(bufferView=len(views) - 1, componentType=gl.FLOAT, count=len(array), type=kind,
                                     **bounds))
        attributes[name] = len(accessors) - 1
        blob += array.tobytes()
    primitive = gl.Primitive(attributes=gl.Attributes(), mode=gl.POINTS,
                             extensions={EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}})
    primitive.attributes = attributes  # the extension's semantics are not pygltflib's known attribute names
    doc = gl.GLTF2(asset=gl.Asset(version="2.0", generator="streamstgs"), scene=0, scenes=[gl.Scene(nodes=[0])],
                   nodes=[gl.Node(mesh=0)], meshes=[gl.Mesh(primitives=[primitive])], accessors=accessors,
                   bufferViews=views, buffers=[gl.Buffer(byteLength=len(blob))], extensionsUsed=[EXTENSION])
    doc.set_binary_blob(bytes(blob))
    return b"".join(doc.save_to_bytes())


def _chunks(data: bytes, where: str) -> tuple[dict, bytes]:
    """The JSON document and binary chunk of a glb, with their sizes checked against the file's."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise InteropError(f"{where}: not a binary glTF (no glTF magic)")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2 or length != len(data):
        raise InteropError(f"{where}: glb version {version}, length {length} (the file has {len(data)} bytes)")
    json_len, json_type = struct.unpack_from("<II", data, 12)
    if json_type != 0x4E4F534A or json_len > min(MAX_JSON_BYTES, len(data) - 20):
        raise InteropError(f"{where}: glb JSON chunk missing or too large")
    try:
        doc = json.loads(data[20:20 + json_len])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InteropError(f"{where}: glb JSON unreadable ({exc})") from None
    at = 20 + json_len
    blob = b""
    if at + 8 <= len(data):
        bin_len, bin_type = struct.unpack_from("<II", data, at)
        if bin_type != 0x004E4942 or at + 8 + bin_len > len(data):
            raise InteropError(f"{where}: glb binary chunk truncated")
        blob = data[at + 8:at + 8 + bin_len]
    return doc, blob


def _column(doc: dict, blob: bytes, index: object, kind: str, count: int, where: str, name: str) -> np.ndarray:
    try:
        accessor = doc["accessors"][index]
        view = doc["bufferViews"][accessor["bufferView"]]
        offset = int(view.get("byteOffset", 0)) + int(accessor.get("byteOffset", 0))
        ok = (accessor["componentType"] == gl.FLOAT and accessor["type"] == kind and accessor["count"] == count
              and view.get("buffer", 0) == 0 and view.get("byteStride", 4 * TYPES[kind]) == 4 * TYPES[kind]
              and not accessor.get("sparse"))
    except (KeyError, IndexError, TypeError, ValueError):
        raise InteropError(f"{where}: attribute {name} has no valid accessor") from None
    size = 4 * TYPES[kind] * count
    if not ok or offset < 0 or offset + size > len(blob):
        raise InteropError(f"{where}: attribute {name} is not {count} float {kind} values inside the binary chunk")
    values = np.frombuffer(blob, "<f4", TYPES[kind] * count, offset).astype(np.float32)
    return values if kind == "SCALAR" else values.reshape(count, TYPES[kind])


def decode(data: bytes, where: str) -> Splats:
    doc, blob = _chunks(data, where)
    try:
        primitives = [p for m in doc.get("meshes", []) for p in m.get("primitives", [])
                      if EXTENSION in (p.get("extensions") or {})]
        attributes = primitives[0]["attributes"]
        count = int(doc["accessors"][attributes["POSITION"]]["count"])
    except (IndexError, KeyError, TypeError, AttributeError, ValueError):
        raise InteropError(f"{where}: no {EXTENSION} primitive with POSITION") from None
    if len(primitives) > 1:
        raise InteropError(f"{where}: {len(primitives)} {EXTENSION} primitives (one is supported)")
    if not 0 < count <= MAX_SPLATS:
        raise InteropError(f"{where}: {count} Gaussians (between 1 and {MAX_SPLATS} are supported)")
    needed = {"POSITION": "VEC3", f"{PREFIX}ROTATION": "VEC4", f"{PREFIX}SCALE": "VEC3", f"{PREFIX}OPACITY": "SCALAR"}
    k = 1
    while sh_attribute(k) in attributes:
        k += 1
    try:
        degree_of(k)
    except ValueError:
        raise InteropError(f"{where}: {k} spherical-harmonics coefficients make no whole degree") from None
    cols = {name: _column(doc, blob, attributes.get(name), kind, count, where, name) for name, kind in
            (needed | {sh_attribute(i): "VEC3" for i in range(coefficients(degree_of(k)))}).items()}
    for name, values in cols.items():
        if not np.isfinite(values).all():
            raise InteropError(f"{where}: attribute {name} holds non-finite values")
    scale, opacity = cols[f"{PREFIX}SCALE"], cols[f"{PREFIX}OPACITY"]
    if (scale < 0).any() or (opacity < 0).any() or (opacity > 1).any():
        raise InteropError(f"{where}: scales must be >= 0 and opacities within [0, 1]")
    log_scales, logits = log_scales_of(scale), logits_of(opacity)
    xyzw = cols[f"{PREFIX}ROTATION"]
    sh = np.stack([cols[sh_attribute(i)] for i in range(k)], 1)
    return Splats(cols["POSITION"], log_scales, xyzw[:, [3, 0, 1, 2]], logits, sh).check(where)
