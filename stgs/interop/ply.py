"""The INRIA 3DGS PLY (binary little-endian), as the reference 3DGS code, gsplat and Nerfstudio's splatfacto write
it, read and written with plyfile.

One `vertex` element, float32 properties: x y z, nx ny nz (zero), f_dc_0..2, f_rest_0..3K-1 (channel-major: all
of red's higher coefficients, then green's, then blue's), opacity (logit), scale_0..2 (log), rot_0..3 (wxyz).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from stgs.interop.sh import coefficients, degree_of
from stgs.interop.splats import MAX_SPLATS, InteropError, Splats

MAX_HEADER_BYTES = 1 << 16
"""Longest PLY header read."""
SCALAR_PROPS = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
TAIL_PROPS = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def properties(degree: int) -> list[str]:
    """The vertex properties of a file of `degree`, in the order the reference code writes them."""
    rest = [f"f_rest_{i}" for i in range(3 * (coefficients(degree) - 1))]
    return [*SCALAR_PROPS, *rest, *TAIL_PROPS]


def encode(splats: Splats) -> bytes:
    splats.check("PLY")
    n, degree = splats.count, splats.sh_degree
    names = properties(degree)
    table = np.zeros(n, dtype=[(name, "<f4") for name in names])
    for i, axis in enumerate("xyz"):
        table[axis] = splats.means[:, i]
        table[f"scale_{i}"] = splats.log_scales[:, i]
        table[f"f_dc_{i}"] = splats.sh[:, 0, i]
    rest = splats.sh[:, 1:].transpose(0, 2, 1).reshape(n, -1)  # channel-major
    for i in range(rest.shape[1]):
        table[f"f_rest_{i}"] = rest[:, i]
    table["opacity"] = splats.opacity_logits
    for i in range(4):
        table[f"rot_{i}"] = splats.quats[:, i]
    out = io.BytesIO()
    PlyData([PlyElement.describe(table, "vertex")], text=False, byte_order="<").write(out)
    return out.getvalue()


TYPE_BYTES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _vertex_count(data: bytes, where: str) -> int:
    """The vertex count of the header, checked (with the bytes a binary file needs for it) before plyfile
    allocates anything."""
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if not data.startswith(b"ply") or end < 0:
        raise InteropError(f"{where}: not a PLY file (no 'ply' magic or no end_header in its first "
                           f"{MAX_HEADER_BYTES} bytes)")
    count, row, element, binary = None, 0, None, False
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if words[:1] == ["format"]:
            binary = len(words) > 1 and words[1].startswith("binary")
        elif words[:1] == ["element"]:
            element = words[1] if len(words) > 1 else None
            if element == "vertex":
                if len(words) != 3 or not words[2].isdigit():
                    raise InteropError(f"{where}: malformed '{line.strip()}'")
                count = int(words[2])
        elif words[:1] == ["property"] and element == "vertex":
            if len(words) != 3 or words[1] not in TYPE_BYTES:
                raise InteropError(f"{where}: vertex property '{line.strip()}' is not a scalar of a known type")
            row += TYPE_BYTES[words[1]]
    if count is None:
        raise InteropError(f"{where}: no 'element vertex N' in the PLY header")
    if not 0 < count <= MAX_SPLATS:
        raise InteropError(f"{where}: {count} vertices (between 1 and {MAX_SPLATS} are supported)")
    body = len(data) - data.index(b"\n", end) - 1
    if binary and body < count * row:
        raise InteropError(f"{where}: truncated: {count} vertices of {row} bytes need {count * row} bytes, the file "
                           f"has {body} after its header")
    return count


def decode(data: bytes, where: str) -> Splats:
    """The Gaussians of a 3DGS PLY; InteropError for anything else (truncated, wrong properties, non-finite)."""
    count = _vertex_count(data, where)
    try:
        ply = PlyData.read(io.BytesIO(data))
    except (PlyParseError, ValueError, EOFError, IndexError) as exc:
        raise InteropError(f"{where}: unreadable PLY ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
                           ) from None
    if "vertex" not in ply or ply["vertex"].count != count:
        raise InteropError(f"{where}: no vertex element of {count} Gaussians")
    vertex = ply["vertex"].data
    names = set(vertex.dtype.names)
    rest = sorted((p for p in names if p.startswith("f_rest_")), key=lambda p: int(p[7:]) if p[7:].isdigit() else -1)
    missing = [p for p in (*SCALAR_PROPS[:3], *SCALAR_PROPS[6:], *TAIL_PROPS) if p not in names]
    if missing:
        raise InteropError(f"{where}: not a 3DGS PLY: no property {', '.join(missing)}")
    if len(rest) % 3 or [int(p[7:]) for p in rest] != list(range(len(rest))):
        raise InteropError(f"{where}: {len(rest)} f_rest properties do not make 3 channels of coefficients")
    try:
        degree = degree_of(len(rest) // 3 + 1)
    except ValueError as exc:
        raise InteropError(f"{where}: {exc}") from None
    column = lambda name: np.asarray(vertex[name], dtype=np.float32)  # noqa: E731
    stack = lambda names_: np.stack([column(p) for p in names_], 1)  # noqa: E731
    k = coefficients(degree)
    sh = np.empty((count, k, 3), dtype=np.float32)
    sh[:, 0] = stack(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        sh[:, 1:] = stack(rest).reshape(count, 3, k - 1).transpose(0, 2, 1)
    splats = Splats(stack(["x", "y", "z"]), stack(["scale_0", "scale_1", "scale_2"]),
                    stack(["rot_0", "rot_1", "rot_2", "rot_3"]), column("opacity"), sh)
    return splats.check(where)


def read(path: Path) -> Splats:
    return decode(Path(path).read_bytes(), str(path))
