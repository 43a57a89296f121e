"""The few ISO BMFF (MP4) operations DASH segmenting needs, with every size checked.

- split a fragmented MP4 (ftyp moov moof mdat [mfra]) into an init segment
  (ftyp + moov) and a media segment (styp + moof + mdat);
- set a media segment's sequence number (mfhd) and decode time (tfdt) so it
  sits at its place in the Representation's timeline, and read them back (with
  the track's timescale) so a client can tell a segment of another GOP;
- read the hvcC of an init segment and form its RFC 6381 codecs string.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass


class MP4Error(ValueError):
    """Malformed or unexpected MP4 data."""


@dataclass
class Box:
    type: str
    start: int
    """Offset of the box header in the buffer."""
    header: int
    """Header length (8, or 16 with a 64-bit size)."""
    end: int
    """Offset just past the box."""

    @property
    def body(self) -> int:
        return self.start + self.header


def iter_boxes(data: bytes | bytearray, start: int = 0, end: int | None = None) -> Iterator[Box]:
    """Boxes laid end to end in data[start:end]; raises MP4Error on any size that does not fit."""
    end = len(data) if end is None else end
    pos = start
    while pos < end:
        if end - pos < 8:
            raise MP4Error(f"truncated box header at offset {pos}")
        size, kind = struct.unpack_from(">I4s", data, pos)
        header = 8
        if size == 1:
            if end - pos < 16:
                raise MP4Error(f"truncated 64-bit box header at offset {pos}")
            size = struct.unpack_from(">Q", data, pos + 8)[0]
            header = 16
        elif size == 0:
            size = end - pos
        if size < header or pos + size > end:
            raise MP4Error(f"box {kind!r} at offset {pos} claims {size} bytes; {end - pos} remain")
        yield Box(kind.decode("latin-1"), pos, header, pos + size)
        pos += size


def find_path(data: bytes | bytearray, path: list[str], start: int = 0, end: int | None = None,
              skips: dict[str, int] | None = None) -> Box:
    """The box at `path` (e.g. ['moov', 'trak']); `skips` gives bytes to skip inside a box before its children."""
    skips = skips or {}
    box = None
    for kind in path:
        found = next((b for b in iter_boxes(data, start, end) if b.type == kind), None)
        if found is None:
            raise MP4Error(f"no {'/'.join(path)} box")
        box = found
        start, end = box.body + skips.get(kind, 0), box.end
    if box is None:
        raise MP4Error("an empty box path")
    return box


def split_fragmented(data: bytes) -> tuple[bytes, bytes]:
    """(init, media) of a single-fragment fMP4; the media segment gets an 'styp' box."""
    boxes = list(iter_boxes(data))
    kinds = [b.type for b in boxes]
    if kinds[:2] != ["ftyp", "moov"] or kinds.count("moof") != 1 or "mdat" not in kinds:
        raise MP4Error(f"expected ftyp moov moof mdat, got {' '.join(kinds)}")
    init = data[boxes[0].start:boxes[1].end]
    moof = boxes[kinds.index("moof")]
    mdat = boxes[kinds.index("mdat")]
    styp = make_box("styp", b"msdh" + struct.pack(">I", 0) + b"msdhmsix")
    return init, styp + data[moof.start:mdat.end]


def make_box(kind: str, body: bytes) -> bytes:
    return struct.pack(">I4s", 8 + len(body), kind.encode("latin-1")) + body


def set_timeline(media: bytes, sequence: int, decode_time: int) -> bytes:
    """Media segment with mfhd.sequence_number and every tfdt.baseMediaDecodeTime replaced."""
    out = bytearray(media)
    moof = find_path(out, ["moof"])
    mfhd = find_path(out, ["mfhd"], moof.body, moof.end)
    struct.pack_into(">I", out, mfhd.body + 4, sequence)
    for traf in (b for b in iter_boxes(out, moof.body, moof.end) if b.type == "traf"):
        tfdt = find_path(out, ["tfdt"], traf.body, traf.end)
        version = out[tfdt.body]
        if version == 1:
            struct.pack_into(">Q", out, tfdt.body + 4, decode_time)
        elif decode_time < 1 << 32:
            struct.pack_into(">I", out, tfdt.body + 4, decode_time)
        else:
            raise MP4Error("decode time needs a version-1 tfdt")
    return bytes(out)


def media_timeline(media: bytes) -> tuple[int, int]:
    """(mfhd.sequence_number, tfdt.baseMediaDecodeTime of the first traf) of a media segment."""
    moof = find_path(media, ["moof"])
    mfhd = find_path(media, ["mfhd"], moof.body, moof.end)
    if mfhd.end - mfhd.body < 8:
        raise MP4Error("mfhd box is truncated")
    sequence = struct.unpack_from(">I", media, mfhd.body + 4)[0]
    tfdt = find_path(media, ["traf", "tfdt"], moof.body, moof.end)
    version = media[tfdt.body] if tfdt.end > tfdt.body else -1
    if version not in (0, 1) or tfdt.end - tfdt.body < (12 if version == 1 else 8):
        raise MP4Error("tfdt box is truncated or of an unknown version")
    decode_time = struct.unpack_from(">Q" if version == 1 else ">I", media, tfdt.body + 4)[0]
    return sequence, decode_time


def track_timescale(init: bytes) -> int:
    """The mdhd timescale (ticks per second) of an init segment's first track."""
    mdhd = find_path(init, ["moov", "trak", "mdia", "mdhd"])
    version = init[mdhd.body] if mdhd.end > mdhd.body else -1
    offset = {0: 12, 1: 20}.get(version)
    if offset is None or mdhd.end - mdhd.body < offset + 4:
        raise MP4Error("mdhd box is truncated or of an unknown version")
    timescale = struct.unpack_from(">I", init, mdhd.body + offset)[0]
    if timescale == 0:
        raise MP4Error("mdhd timescale is 0")
    return timescale


_STSD_HEADER = 8
"""Bytes of stsd before its sample entries (FullBox header + entry count)."""
_VISUAL_SAMPLE_ENTRY = 78
"""Bytes of a visual sample entry before its child boxes."""


def sample_entry_config(init: bytes, kinds: tuple[str, ...], config: str, codec: str) -> tuple[str, bytes]:
    """(type, `config` box payload) of an init segment's first sample entry, which must be one of `kinds`
    (e.g. ('hvc1', 'hev1') with 'hvcC'); `codec` names it in the error."""
    stsd = find_path(init, ["moov", "trak", "mdia", "minf", "stbl", "stsd"])
    entry = next(iter_boxes(init, stsd.body + _STSD_HEADER, stsd.end), None)
    if entry is None or entry.type not in kinds:
        raise MP4Error(f"init segment has no {codec} sample entry")
    box = find_path(init, [config], entry.body + _VISUAL_SAMPLE_ENTRY, entry.end)
    return entry.type, init[box.body:box.end]


def hevc_codecs(init: bytes) -> str:
    """RFC 6381 codecs string (e.g. 'hvc1.4.10.L90.9D.88') from an init segment's hvcC."""
    kind, b = sample_entry_config(init, ("hvc1", "hev1"), "hvcC", "HEVC")
    if len(b) < 13:
        raise MP4Error("hvcC box is truncated")
    space, tier, profile = b[1] >> 6, (b[1] >> 5) & 1, b[1] & 0x1F
    compat = int.from_bytes(b[2:6], "big")
    compat_rev = int(f"{compat:032b}"[::-1], 2)
    constraints = list(b[6:12])
    while constraints and constraints[-1] == 0:
        constraints.pop()
    level = b[12]
    parts = [kind, f"{'' if space == 0 else 'ABC'[space - 1]}{profile}", f"{compat_rev:X}",
             f"{'LH'[tier]}{level}"]
    parts += [f"{c:X}" for c in constraints]
    return ".".join(parts)
