"""Splat files by name: the format from the suffix (or given), atomic writes, and frame sequences with an index."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from stgs.fsio import atomic_write_bytes
from stgs.interop import gltf, ply, spz
from stgs.interop.splats import InteropError, Splats

FORMATS: dict[str, tuple[Callable[[Splats], bytes], Callable[[bytes, str], Splats]]] = {
    "ply": (ply.encode, ply.decode), "spz": (spz.encode, spz.decode), "glb": (gltf.encode, gltf.decode)}
"""Format name (also the file suffix) -> (encode, decode)."""
MAX_FILE_BYTES = 4 << 30
"""Largest splat file read."""
SEQUENCE_INDEX = "sequence.json"
SEQUENCE_FORMAT = "streamstgs-splat-sequence"


def format_of(path: Path, given: str | None = None) -> str:
    name = given or Path(path).suffix.lower().lstrip(".")
    if name not in FORMATS:
        raise InteropError(f"{path}: unknown splat format {name!r} (known: {', '.join(FORMATS)})")
    return name


def read_splats(path: Path, fmt: str | None = None) -> Splats:
    """The Gaussians of a PLY, SPZ or glb file (InteropError naming the file for anything unreadable)."""
    path = Path(path)
    kind = format_of(path, fmt)
    if not path.is_file():
        raise InteropError(f"{path}: no such file")
    if path.stat().st_size > MAX_FILE_BYTES:
        raise InteropError(f"{path}: {path.stat().st_size} bytes is larger than the {MAX_FILE_BYTES >> 30} GiB read")
    return FORMATS[kind][1](path.read_bytes(), str(path))


def write_splats(path: Path, splats: Splats, fmt: str | None = None) -> int:
    """Write atomically (nothing at `path` unless the whole file is); returns its size in bytes."""
    data = FORMATS[format_of(path, fmt)][0](splats)
    atomic_write_bytes(Path(path), data)
    return len(data)


def frame_name(frame: int, fmt: str) -> str:
    return f"frame_{frame:06d}.{fmt}"


def write_sequence(folder: Path, frames: list[int], splats_of: Callable[[int], Splats], fmt: str, fps: float,
                   source: str, progress: Callable[[int], None] | None = None) -> dict:
    """One file per frame in `folder` and the index, sequence.json (removed first, written last: a folder with an
    index is whole): {"format", "version", "fps", "source", "files": [{"frame", "file", "bytes", "count"}]}."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InteropError(f"{folder}: exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / SEQUENCE_INDEX).unlink(missing_ok=True)  # an earlier index no longer describes the folder
    rows = []
    for frame in frames:
        splats = splats_of(frame)
        name = frame_name(frame, fmt)
        rows.append({"frame": frame, "file": name, "bytes": write_splats(folder / name, splats, fmt),
                     "count": splats.count})
        if progress is not None:
            progress(frame)
    doc = {"format": SEQUENCE_FORMAT, "version": 1, "fps": fps, "source": source, "splat_format": fmt,
           "files": rows}
    atomic_write_bytes(folder / SEQUENCE_INDEX, (json.dumps(doc, indent=1) + "\n").encode())
    return doc
