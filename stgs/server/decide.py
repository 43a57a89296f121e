"""What to answer for a GET/HEAD of a file, decided from the request's headers and the file's stat alone, before
any byte is read (as aiohttp's FileResponse does): 200, 206, 304, 412 or 416, with the span of the file to send.

RFC 9110 order: If-Match / If-Unmodified-Since (412), then If-None-Match / If-Modified-Since (304), then
If-Range and Range (206 or 416; a Range that If-Range rules out gives the whole file). aiohttp's request parses
the validators; If-Range's entity-tag form and the Range header are read here (aiohttp reads If-Range as a date
only, and answers a zero-length suffix, another unit or several ranges against RFC 9110)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from aiohttp import web
from aiohttp.helpers import ETAG_ANY, ETag

from stgs.server.files import etag_of, file_validators

CONDITIONAL_HEADERS = ("Range", "If-Range", "If-None-Match", "If-Modified-Since", "If-Match",
                       "If-Unmodified-Since")
"""Without any of these, the answer is a plain 200 of the whole file, decided without parsing anything."""


@dataclass(frozen=True)
class Answer:
    """A decided file response: its status, the headers it adds and the span of the file its body carries."""

    status: int
    headers: dict[str, str]
    offset: int = 0
    count: int = 0
    """Body bytes (0 for 304, 412 and 416; HEAD sends none whatever this says)."""


def matches(etag: str, tags: tuple[ETag, ...], weak: bool) -> bool:
    if len(tags) == 1 and tags[0].value == ETAG_ANY:
        return True
    return any(tag.value == etag for tag in tags if weak or not tag.is_weak)


def decide(request: web.BaseRequest, size: int, mtime_ns: int, mtime: float) -> Answer:
    """The answer to a GET/HEAD of a file of `size` bytes last modified at `mtime` (`mtime_ns`)."""
    validators = file_validators(size, mtime_ns, mtime)
    if not any(name in request.headers for name in CONDITIONAL_HEADERS):
        return Answer(200, validators, 0, size)
    etag = etag_of(size, mtime_ns)
    if_match = request.if_match
    if if_match is not None and not matches(etag, if_match, weak=False):
        return Answer(412, {"Content-Length": "0"})
    since = request.if_unmodified_since
    if if_match is None and since is not None and mtime > since.timestamp():
        return Answer(412, {"Content-Length": "0"})
    unchanged = {name: validators[name] for name in ("ETag", "Last-Modified")}
    if_none_match = request.if_none_match
    if if_none_match is not None and matches(etag, if_none_match, weak=True):
        return Answer(304, unchanged)
    since = request.if_modified_since
    if if_none_match is None and since is not None and mtime <= since.timestamp():
        return Answer(304, unchanged)
    if "Range" not in request.headers or not range_applies(request, etag, mtime):
        return Answer(200, validators, 0, size)
    return range_answer(request, size, validators)


def range_applies(request: web.BaseRequest, etag: str, mtime: float) -> bool:
    """If-Range: the Range counts only if the client's copy is the current one (strong ETag, or a date no
    earlier than the file's modification)."""
    value = request.headers.get("If-Range")
    if value is None:
        return True
    if value.startswith('"'):
        return value == f'"{etag}"'
    if value.startswith("W/"):
        return False  # a weak tag never validates a range
    date = request.if_range
    return date is not None and mtime <= date.timestamp()


_RANGE_SPEC = re.compile(r"(\d{1,19})-(\d{0,19})|-(\d{1,19})")
"""One byte-range-spec: first-[last], or -suffix (RFC 9110 §14.1.2); 19 digits keep every number an int64."""


def byte_span(header: str, size: int) -> tuple[int, int] | Literal[False] | None:
    """The [start, stop) to send for a Range header: a span; None to ignore the header and send the whole file
    (another unit, several ranges one of which is satisfiable: we send no multipart); False if unsatisfiable
    (invalid specs, or none inside the file, or a zero-length suffix)."""
    unit, sep, specs = header.partition("=")
    if not sep or unit.strip().lower() != "bytes":
        return None
    spans, parts = [], specs.split(",")
    for spec in parts:
        match = _RANGE_SPEC.fullmatch(spec.strip())
        if match is None:
            return False
        first, last, suffix = match.groups()
        if suffix is not None:
            span = (max(0, size - int(suffix)), size) if int(suffix) > 0 else None
        elif last and int(last) < int(first):
            return False
        else:
            stop = size if not last else min(int(last) + 1, size)
            span = (int(first), stop) if int(first) < size else None
        if span is not None and span[0] < span[1]:
            spans.append(span)
    if not spans:
        return False
    return spans[0] if len(parts) == 1 else None


def range_answer(request: web.BaseRequest, size: int, validators: dict[str, str]) -> Answer:
    span = byte_span(request.headers["Range"], size)
    if span is None:
        return Answer(200, validators, 0, size)
    if span is False:
        return Answer(416, {"Content-Range": f"bytes */{size}", "Content-Length": "0"})
    start, stop = span
    count = stop - start
    headers = {**validators, "Content-Length": str(count), "Content-Range": f"bytes {start}-{stop - 1}/{size}"}
    return Answer(206, headers, start, count)
