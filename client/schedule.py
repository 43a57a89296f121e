"""The fetch schedule: what to request next and what to make of each outcome, with no I/O (sans-IO).

One schedule serves two drivers: the player (`stgs.client.player`) performs
each `Request` with aiohttp on the wall clock, the simulator
(`stgs.harness.sim`) on a virtual clock over a modelled network. Both send
back what happened (`Done`, `Failed`, `Abandoned`) and the schedule decides
the rest, so the two cannot drift apart:

- GOP k: its keyframe first (not adaptive, and a throughput sample), then
  the ABR rule picks the feature rung with that keyframe's exact size in its
  budget; the rung's init segment once per Representation; the media
  segment, judged by the abandonment rule while it arrives.
- A transient failure (connection error, timeout, truncated body, HTTP
  408/429/5xx) is retried with exponential backoff (`Wait`), up to
  `DownloadSettings.retries` times.
- A feature download that is abandoned, or fails for good above the lowest
  rung, falls back to the lowest rung; a failure at the lowest rung, or of a
  keyframe, ends the playback (`ScheduleError`).
- A keyframe the decoder rejects is downloaded once more
  (`refetch_keyframe`); a feature segment that does not decode falls back
  to the lowest rung (`fallback`).

Every request and decision is appended to the GOP's record (`requests`,
`decisions`, `events`): the playback log tells what was fetched and why.
Times are media seconds on the driver's clock.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Generator
from dataclasses import dataclass, field

from stgs.client.abr import (
    AbandonRule,
    AbrRule,
    AbrSettings,
    AbrState,
    Decision,
    FixedRule,
    InFlight,
    ThroughputSample,
    throughput_kbps,
)
from stgs.client.download import DownloadSettings
from stgs.client.manifest import Presentation
from stgs.client.playlog import GOPRecord
from stgs.limits import MAX_INIT_BYTES
from stgs.tree import KEYFRAME_REP


class ScheduleError(Exception):
    """A GOP cannot be fetched (after the retries and fallbacks the log records)."""


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
    judge: Callable[[int, int | None, float], Decision | None] | None = None
    """For an abandonable download: (bytes so far, Content-Length, media seconds since the request started)
    -> a Decision to drop it, or None to go on."""
    time_left: float | None = None
    """Media seconds this attempt may take: what the request's deadline leaves after earlier attempts."""


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


Outcome = Done | Failed | Abandoned
Step = Generator[Request | Wait, Outcome | None, "Fetched"]


@dataclass
class Fetched:
    """A GOP's downloaded parts (bytes where the driver has them)."""

    index: int
    rung: int
    keyframe: bytes | None = None
    init: bytes | None = None
    media: bytes | None = None


@dataclass
class FetchSchedule:
    """The fetch policy of one playback (see the module docstring)."""

    pres: Presentation
    rule: AbrRule
    buffer_level: Callable[[], float]
    """The driver's buffer level now (media seconds downloaded ahead of the playhead)."""
    capacity_s: float
    segment_bits: Callable[[int], list[float] | None] = lambda k: None
    """GOP k's feature bits per rung, where known (stats.json); None: @bandwidth x duration."""
    settings: AbrSettings = field(default_factory=AbrSettings)
    download: DownloadSettings = field(default_factory=DownloadSettings)
    samples: list[ThroughputSample] = field(default_factory=list)
    inits: dict[str, bytes | None] = field(default_factory=dict)
    current: int | None = None
    """Rung of the last GOP fetched."""
    wasted_bytes: int = 0
    retries: int = 0

    def __post_init__(self) -> None:
        self.abandon = AbandonRule(self.settings)
        self.adaptive = not isinstance(self.rule, FixedRule)

    # --- one GOP ---

    def fetch_gop(self, k: int, rec: GOPRecord) -> Step:
        """GOP k: keyframe, the ABR decision, init (once per Representation) and media, with fallbacks."""
        keyframe = yield from self._get(self._request("keyframe", k, KEYFRAME_REP), rec)
        if not isinstance(keyframe, Done):
            raise ScheduleError(f"GOP {k}: {keyframe.reason}")
        rec.keyframe_bytes = keyframe.nbytes
        state = self._state(k, keyframe.nbytes * 8)
        decision = self.rule.choose(state)
        self._decided(rec, decision)
        rec.rule, rec.buffer_s = decision.rule, state.buffer_s
        rec.estimate_kbps = throughput_kbps(state.samples, self.settings)
        fetched = yield from self._features(k, decision.index, state, rec)
        fetched.keyframe = keyframe.data
        self.current = fetched.rung
        return fetched

    def refetch_keyframe(self, k: int, rec: GOPRecord, reason: str) -> Step:
        """GOP k's keyframe once more, after the decoder rejected it (damaged in transit?)."""
        rec.events.append(f"keyframe rejected, downloaded again: {reason}")
        keyframe = yield from self._get(self._request("keyframe", k, KEYFRAME_REP), rec)
        if not isinstance(keyframe, Done):
            raise ScheduleError(f"GOP {k}: {keyframe.reason}")
        return Fetched(k, -1, keyframe=keyframe.data)

    def fallback(self, k: int, rec: GOPRecord, rung: int, reason: str) -> Step:
        """GOP k's features at the lowest rung, after those of `rung` did not decode."""
        if rung == 0:
            raise ScheduleError(f"feature segment of GOP {k}: {reason}")
        rec.events.append(f"fallback from {rec.rep}: feature segment does not decode ({reason})")
        self._decided(rec, Decision(0, "fallback", f"{rec.rep} does not decode"))
        return (yield from self._lowest(k, rec))

    # --- parts ---

    def _features(self, k: int, rung: int, state: AbrState, rec: GOPRecord) -> Step:
        rep = self.pres.ladder[rung].rep_id
        init = yield from self._init(rep, rec)
        if isinstance(init, Failed):
            failure: Failed | Abandoned = init
        else:
            judge = self._judge(rung, state) if self.adaptive and rung > 0 else None
            media = yield from self._get(self._request("media", k, rep, judge), rec)
            if isinstance(media, Done):
                return self._chosen(k, rung, rec, media)
            failure = media
        if isinstance(failure, Abandoned):
            self.samples.append(ThroughputSample(failure.nbytes, failure.seconds))
            rec.abandoned_bytes += failure.nbytes
            self.wasted_bytes += failure.nbytes
            rec.events.append(f"abandoned {rep} after {failure.nbytes} bytes ({failure.seconds:.2f} s)")
            self._decided(rec, failure.decision)
        elif rung == 0:
            raise ScheduleError(f"GOP {k}: {failure.reason}")
        else:
            rec.events.append(f"fallback from {rep}: {failure.reason}")
            self._decided(rec, Decision(0, "fallback", failure.reason))
        return (yield from self._lowest(k, rec))

    def _lowest(self, k: int, rec: GOPRecord) -> Step:
        low = self.pres.ladder[0].rep_id
        init = yield from self._init(low, rec)
        if isinstance(init, Failed):
            raise ScheduleError(f"GOP {k}: {init.reason}")
        media = yield from self._get(self._request("media", k, low), rec)
        if not isinstance(media, Done):
            raise ScheduleError(f"GOP {k}: {media.reason}")
        return self._chosen(k, 0, rec, media)

    def _init(self, rep: str, rec: GOPRecord) -> Generator[Request | Wait, Outcome | None, Outcome | None]:
        """The init segment of `rep`, downloaded once (its bytes count to the GOP that needed it first);
        None when it was downloaded before."""
        if rep in self.inits:
            return None
        outcome = yield from self._get(self._request("init", rec.index, rep), rec)
        if isinstance(outcome, Done):
            self.inits[rep] = outcome.data
            rec.init_bytes += outcome.nbytes
        return outcome

    def _get(self, request: Request, rec: GOPRecord) -> Generator[Request | Wait, Outcome | None, Outcome]:
        """One request with its retries, all within the request's deadline (DownloadSettings.total_timeout_s);
        keyframe and media downloads are throughput samples."""
        settings = self.download
        outcome: Outcome | None = None
        spent = 0.0
        for attempt in range(settings.retries + 1):
            if isinstance(outcome, Failed):
                wait = settings.backoff(attempt)
                if spent + wait >= settings.total_timeout_s:
                    outcome = Failed(f"{outcome.reason}; no answer within {settings.total_timeout_s:g} s",
                                     retryable=True, seconds=spent)
                    break
                self.retries += 1
                rec.events.append(f"retry {attempt} of the {request.kind} of {request.rep}: {outcome.reason}")
                yield Wait(wait)
                spent += wait
            outcome = yield dataclasses.replace(request, time_left=settings.total_timeout_s - spent)
            spent += outcome.seconds
            rec.requests.append({"kind": request.kind, "rep": request.rep, "outcome": _describe(outcome)})
            if not (isinstance(outcome, Failed) and outcome.retryable):
                break
        else:
            if settings.retries:
                outcome = Failed(f"{outcome.reason} (after {settings.retries + 1} attempts)", retryable=True,
                                 seconds=spent)
        if isinstance(outcome, Done) and request.kind in ("keyframe", "media"):
            self.samples.append(ThroughputSample(outcome.nbytes, outcome.seconds))
        return outcome

    def _request(self, kind: str, k: int, rep: str,
                 judge: Callable[[int, int | None, float], Decision | None] | None = None) -> Request:
        """The request for a part of GOP k: its URL and its size cap from the manifest."""
        pres = self.pres
        if kind == "keyframe":
            return Request(kind, k, rep, pres.keyframe_url(k), pres.max_keyframe_bytes(), judge)
        if kind == "init":
            return Request(kind, k, rep, pres.init_url(rep), MAX_INIT_BYTES, judge)
        return Request(kind, k, rep, pres.media_url(rep, k), pres.max_media_bytes(rep), judge)

    def _judge(self, rung: int, state: AbrState) -> Callable[[int, int | None, float], Decision | None]:
        def judge(received: int, total: int | None, elapsed_s: float) -> Decision | None:
            flight = InFlight(rung, received, total, elapsed_s)
            return self.abandon.choose(dataclasses.replace(state, buffer_s=self.buffer_level(), in_flight=flight))

        return judge

    def _chosen(self, k: int, rung: int, rec: GOPRecord, media: Done) -> Fetched:
        r = self.pres.ladder[rung]
        rec.rep, rec.qp, rec.feature_bytes, rec.ttfb_s = r.rep_id, r.qp, rec.feature_bytes + media.nbytes, media.ttfb
        return Fetched(k, rung, init=self.inits.get(r.rep_id), media=media.data)

    def _state(self, k: int, keyframe_bits: float) -> AbrState:
        ladder = self.pres.ladder
        return AbrState([r.bandwidth for r in ladder], self.pres.segment_seconds, self.buffer_level(),
                        self.capacity_s, list(self.samples), keyframe_bits, self.segment_bits(k), self.current)

    @staticmethod
    def _decided(rec: GOPRecord, decision: Decision) -> None:
        rec.decisions.append(decision.to_json())


def _describe(outcome: Outcome | None) -> str:
    if isinstance(outcome, Done):
        return f"{outcome.nbytes} bytes"
    if isinstance(outcome, Abandoned):
        return f"abandoned after {outcome.nbytes} bytes"
    if isinstance(outcome, Failed):
        return f"failed: {outcome.reason}"
    return "none"
