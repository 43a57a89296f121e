"""The fetch schedule's vocabulary: the steps it yields to its driver (`Request`, `Parallel`, `Wait`), the outcomes
the driver sends back (`Done`, `Failed`, `Abandoned`) and what a GOP's fetch returns (`Fetched`)."""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any, TypeVar

from stgs.client.abr import Decision, ThroughputSample
from stgs.tree import KEYFRAME_REP


class ScheduleError(Exception):
    """A GOP cannot be fetched (after the retries and fallbacks the log records)."""


Judge = Callable[[int, int | None, float, float], Decision | None]
"""(bytes so far, Content-Length, media seconds since the request started, seconds to its first byte) -> a
Decision to drop the download, or None to go on."""


@dataclass(frozen=True)
class Request:
    """One HTTP GET the driver is to perform."""

    kind: str
    """keyframe, init or media."""
    gop: int
    rep: str
    """The Representation (KEYFRAME_REP for keyframes)."""
    url: str
    """Absolute URL, resolved against the MPD's."""
    max_bytes: int
    """The body may not be longer (checked before and while reading)."""
    judge: Judge | None = None
    """For an abandonable download: decides on each arrival whether to drop it."""
    time_left: float | None = None
    """Media seconds this attempt may take: what the request's deadline leaves after earlier attempts."""


@dataclass(frozen=True)
class Parallel:
    """Perform these requests at once; their outcomes come back as a tuple in the same order."""

    requests: tuple[Request, ...]


@dataclass(frozen=True)
class Wait:
    """Sleep this many media seconds before the next request (retry backoff)."""

    seconds: float


@dataclass(frozen=True)
class Done:
    nbytes: int
    seconds: float
    """Request start to last byte (media seconds)."""
    ttfb: float = 0.0
    data: bytes | None = None
    """The body (None where the driver only models sizes)."""


@dataclass(frozen=True)
class Failed:
    reason: str
    retryable: bool
    """A transient failure (worth retrying) rather than a final answer such as 404."""
    seconds: float = 0.0
    """Request start to failure (media seconds)."""


@dataclass(frozen=True)
class Abandoned:
    nbytes: int
    seconds: float
    decision: Decision
    ttfb: float = 0.0

    @property
    def reason(self) -> str:
        return f"abandoned after {self.nbytes} bytes: {self.decision.reason}"


Outcome = Done | Failed | Abandoned

T = TypeVar("T")
Steps = Generator[Request | Wait | Parallel, Any, T]
"""A generator of steps that returns a T. The driver sends back an Outcome for each Request, a tuple of them for
a Parallel and None after a Wait: one type per step, which the type system cannot tie to the step, hence Any."""
Step = Steps["Fetched"]
"""The steps of one GOP's fetch."""


@dataclass
class Fetched:
    """A GOP's downloaded parts (bytes where the driver has them)."""

    index: int
    rung: int
    keyframe: bytes | None = None
    init: bytes | None = None
    media: bytes | None = None
    keyframe_rep: str = KEYFRAME_REP
    """The keyframe Representation `keyframe` is of."""


def throughput_sample(*parts: Done, joint: bool = False) -> ThroughputSample:
    """One throughput sample of transfers made one after the other (or at once, `joint`)."""
    nbytes = sum(p.nbytes for p in parts)
    if joint:
        return ThroughputSample(nbytes, max(p.seconds for p in parts), min(p.ttfb for p in parts))
    return ThroughputSample(nbytes, sum(p.seconds for p in parts), sum(p.ttfb for p in parts))
