"""The MPD's XML values: xs:duration, bounded integer attributes and the hardened parser (every problem an
MPDError, stgs.errors). stgs.mpd.model builds and reads whole documents with them; segment URL templates expand in
stgs.tree, beside the paths they name."""

from __future__ import annotations

import math
import re

from lxml import etree

from stgs.errors import MPDError
from stgs.limits import MAX_DURATION_S


def format_duration(seconds: float) -> str:
    """xs:duration for a non-negative number of seconds, e.g. PT2.5S, PT1H0M3S."""
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"duration must be finite and non-negative, got {seconds}")
    millis = round(seconds * 1000)
    hours, rest = divmod(millis, 3_600_000)
    minutes, rest = divmod(rest, 60_000)
    secs = f"{rest / 1000:.3f}".rstrip("0").rstrip(".")
    if hours:
        return f"PT{hours}H{minutes}M{secs}S"
    if minutes:
        return f"PT{minutes}M{secs}S"
    return f"PT{secs}S"


_DURATION = re.compile(r"^P(?:(\d{1,9})D)?(?:T(?:(\d{1,9})H)?(?:(\d{1,9})M)?(?:(\d{1,12}(?:\.\d{1,9})?)S)?)?$")
"""Days, hours, minutes, seconds: at most 9 digits each (12 for seconds), far beyond any presentation."""


def parse_duration(text: str) -> float:
    """Seconds of an xs:duration without years or months (what MPDs use)."""
    match = _DURATION.match(text.strip()) if text else None
    if not match or text.strip() in ("P", "PT"):
        raise MPDError(f"unsupported duration {text!r}")
    days, hours, minutes, secs = match.groups()
    seconds = int(days or 0) * 86400 + int(hours or 0) * 3600 + int(minutes or 0) * 60 + float(secs or 0.0)
    if seconds > MAX_DURATION_S:
        raise MPDError(f"duration {text!r} is over the {MAX_DURATION_S:.0f}-second limit")
    return seconds


def required_attr(el: etree._Element, attr: str) -> str:
    """The attribute's text; MPDError naming the element and attribute when it is missing."""
    value = el.get(attr)
    if value is None:
        raise MPDError(f"{etree.QName(el).localname} lacks @{attr}")
    return value


UINT32_MAX = (1 << 32) - 1
"""The largest xs:unsignedInt: @bandwidth, @timescale, @duration, @startNumber, @id, @width, @height."""


def int_attr(el: etree._Element, attr: str, default: int | None = None, lo: int = 0, hi: int = UINT32_MAX) -> int:
    """An integer attribute within lo..hi (the schema's xs:unsignedInt by default)."""
    if el.get(attr) is None and default is not None:
        return default
    value = required_attr(el, attr)
    where = f"{etree.QName(el).localname}@{attr}"
    if not re.fullmatch(r"\s*[+-]?\d{1,20}\s*", value):
        raise MPDError(f"{where} is not an integer of at most 20 digits: {value[:40]!r}")
    number = int(value)
    if not lo <= number <= hi:
        raise MPDError(f"{where} is {number}, outside {lo}..{hi}")
    return number


def optional_int_attr(el: etree._Element, attr: str) -> int | None:
    """int_attr's xs:unsignedInt, or None when the attribute is absent."""
    return int_attr(el, attr) if el.get(attr) is not None else None


def secure_parser() -> etree.XMLParser:
    """An XML parser that resolves no entities, loads no DTD and touches no network."""
    return etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False,
                           remove_comments=True)
