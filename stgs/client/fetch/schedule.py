"""The fetch schedule: what to request next and what to make of each outcome, with no I/O (sans-IO).

One schedule serves two drivers: the player (`stgs.client.session`) performs
each `Request` with aiohttp on the wall clock, the simulator
(`stgs.harness.sim`) on a virtual clock over a modelled network. Both send
back what happened (`Done`, `Failed`, `Abandoned`) and the schedule decides
the rest, so the two cannot drift apart:

- GOP k, once there is a throughput sample (or the rung is pinned): the ABR
  rule picks the feature rung with the keyframe's size in its budget
  (stats.json's, else the previous keyframe's), the rung's init segment is
  fetched once per Representation, then the keyframe and the media segment
  are requested together (`Parallel`: one round trip for both) and the
  media is judged by the abandonment rule while it arrives. The first GOP
  of a playback fetches its keyframe first, as its only throughput sample,
  then decides. A part that fails in the joint request is requested alone.
- One throughput sample per GOP: keyframe and features together (round
  trips kept apart as latency); an abandoned transfer is a sample of its own.
- A transient failure (connection error, timeout, truncated body, HTTP
  408/429/5xx) is retried with exponential backoff (`Wait`), up to
  `DownloadSettings.retries` times (stgs.client.fetch.retry).
- A feature download that is abandoned, or fails for good above the lowest
  rung, falls back to the lowest rung; a failure at the lowest rung, or of a
  keyframe, ends the playback (`ScheduleError`).
- A layered (format-2) presentation's static layer is requested first, once
  per playback whatever the start GOP (`fetch_static`), with the same
  retries; it is the first throughput sample. A failure ends the playback.
- A keyframe the decoder rejects is downloaded once more
  (`refetch_keyframe`); a feature segment that does not decode falls back
  to the lowest rung (`fallback`).

Every request and decision is appended to the GOP's record (`requests`,
`decisions`, `events`): the playback log tells what was fetched and why.
Times are media seconds on the driver's clock.
"""

from __future__ import annotations

from collections.abc import Callable
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
    UpcomingGOP,
    throughput_kbps,
)
from stgs.client.fetch.download import DownloadSettings
from stgs.client.fetch.retry import first_attempt, record, with_retries
from stgs.client.fetch.steps import (
    Abandoned,
    Done,
    Failed,
    Fetched,
    Judge,
    Outcome,
    Parallel,
    Request,
    ScheduleError,
    Step,
    Steps,
    throughput_sample,
)
from stgs.client.manifest import Presentation
from stgs.client.playlog import GOPRecord
from stgs.limits import MAX_INIT_BYTES
from stgs.tree import STATIC_REP


@dataclass
class FetchSchedule:
    """The fetch policy of one playback (see the module docstring)."""

    pres: Presentation
    rule: AbrRule
    buffer_level: Callable[[], float]
    """The driver's buffer level now (media seconds downloaded ahead of the playhead)."""
    capacity_s: float
    gop_info: Callable[[int], UpcomingGOP | None] = lambda k: None
    """GOP k's keyframe and per-rung feature bits and PSNR, where the scene says (stats.json)."""
    settings: AbrSettings = field(default_factory=AbrSettings)
    download: DownloadSettings = field(default_factory=DownloadSettings)
    clock: Callable[[], float] = lambda: 0.0
    """The driver's clock (media seconds), to tell how long the fetcher waited for room."""
    playing: Callable[[], bool] = lambda: True
    """Whether playback has started."""
    samples: list[ThroughputSample] = field(default_factory=list)
    inits: dict[str, bytes | None] = field(default_factory=dict)
    current: int | None = None
    """Rung of the last GOP fetched."""
    wasted_bytes: int = 0
    retries: int = 0

    def __post_init__(self) -> None:
        self.abandon = AbandonRule(self.settings)
        self.adaptive = not isinstance(self.rule, FixedRule)
        self._arrived: float | None = None
        self._last_keyframe_bits: float | None = None

    # --- the static layer (format 2), once per playback ---

    def fetch_static(self, rec: GOPRecord) -> Steps[bytes | None]:
        """The static-layer segment, before the first GOP (counted in that GOP's record as its `static` request);
        its transfer is the ABR's first throughput sample. Its body (None where the driver only models sizes)."""
        pres = self.pres
        request = Request("static", rec.index, STATIC_REP, pres.static_url(), pres.max_static_bytes())
        outcome = yield from self._get(request, rec)
        if not isinstance(outcome, Done):
            raise ScheduleError(f"static layer: {outcome.reason}")
        self.samples.append(throughput_sample(outcome))
        rec.static_bytes = outcome.nbytes
        return outcome.data

    # --- one GOP ---

    def fetch_gop(self, k: int, rec: GOPRecord) -> Step:
        """GOP k: the ABR decision, init (once per Representation), keyframe and media, with fallbacks. The keyframe
        is the chosen rung's (its @associationId); one fetched before the decision, as the first GOP's throughput
        probe, is the floor rung's and plays with whichever features the rule then picks."""
        now = self.clock()
        waited = 0.0 if self._arrived is None else max(0.0, now - self._arrived)
        info = self.gop_info(k)
        kf_bits = info.keyframe_bits if info is not None else self._last_keyframe_bits
        if self.download.concurrent and (not self.adaptive or (self.samples and kf_bits is not None)):
            state = self._state(k, kf_bits or 0.0, waited, round_trips=1)
            decision = self._decide(rec, state)
            kf_rep = self.pres.ladder[decision.index].keyframe_rep
            keyframe, fetched = yield from self._together(k, decision.index, state, rec)
        else:
            kf_rep = self.pres.ladder[0].keyframe_rep
            keyframe = yield from self._keyframe(k, rec, kf_rep)
            alone = throughput_sample(keyframe)
            state = self._state(k, self._base_keyframe_bits(keyframe.nbytes * 8, kf_rep), waited, round_trips=2,
                                keyframe_fetched=True, extra=[alone])
            decision = self._decide(rec, state)
            fetched = yield from self._features(k, decision.index, state, rec, keyframe)
        rec.keyframe_bytes = keyframe.nbytes
        rec.keyframe_rep = kf_rep
        self._last_keyframe_bits = self._base_keyframe_bits(keyframe.nbytes * 8, kf_rep)
        fetched.keyframe, fetched.keyframe_rep = keyframe.data, kf_rep
        self.current = fetched.rung
        self._arrived = self.clock()
        return fetched

    def _base_keyframe_bits(self, bits: float, rep: str) -> float:
        """Bits of a keyframe of Representation `rep` as the cheapest keyframes of the ladder would have it (the
        share AbrState.keyframe_bits stands for; Presentation.abr_bandwidths), scaled by their @bandwidth."""
        base = min(r.keyframe_bandwidth for r in self.pres.ladder)
        own = self.pres.keyframe_reps[rep].bandwidth
        return bits * base / own if own > 0 else bits

    # --- parts ---

    def _decide(self, rec: GOPRecord, state: AbrState) -> Decision:
        decision = self.rule.choose(state)
        self._decided(rec, decision)
        rec.rule, rec.buffer_s = decision.rule, state.buffer_s
        rec.estimate_kbps = throughput_kbps(state.samples, self.settings)
        return decision

    def _keyframe(self, k: int, rec: GOPRecord, rep: str) -> Steps[Done]:
        keyframe = yield from self._get(self._request("keyframe", k, rep), rec)
        if not isinstance(keyframe, Done):
            raise ScheduleError(f"GOP {k}: {keyframe.reason}")
        return keyframe

    def _together(self, k: int, rung: int, state: AbrState, rec: GOPRecord) -> Steps[tuple[Done, Fetched]]:
        """Keyframe and media of GOP k in one joint request (after the rung's init segment, if new)."""
        rep, kf_rep = self.pres.ladder[rung].rep_id, self.pres.ladder[rung].keyframe_rep
        init = yield from self._init(rep, rec)
        if isinstance(init, Failed):
            keyframe = yield from self._keyframe(k, rec, kf_rep)
            return keyframe, (yield from self._recover(k, rung, init, rec))
        kf_req = first_attempt(self._request("keyframe", k, kf_rep), self.download)
        media_req = first_attempt(self._request("media", k, rep, self._judge(rung, state)), self.download)
        kf_outcome, media = yield Parallel((kf_req, media_req))
        for req, outcome in ((kf_req, kf_outcome), (media_req, media)):
            record(rec, req, outcome)
        if isinstance(kf_outcome, Done) and isinstance(media, Done):
            self.samples.append(throughput_sample(kf_outcome, media, joint=True))
        if isinstance(kf_outcome, Failed) and kf_outcome.retryable:
            kf_outcome = yield from self._get(kf_req, rec, first=kf_outcome)
        if not isinstance(kf_outcome, Done):
            raise ScheduleError(f"GOP {k}: {kf_outcome.reason}")
        if isinstance(media, Failed) and media.retryable:
            media = yield from self._get(media_req, rec, first=media)
            if isinstance(media, Done):
                self.samples.append(throughput_sample(media))
        if isinstance(media, Done):
            return kf_outcome, self._chosen(k, rung, rec, media)
        return kf_outcome, (yield from self._recover(k, rung, media, rec))

    def _features(self, k: int, rung: int, state: AbrState, rec: GOPRecord, keyframe: Done) -> Step:
        rep = self.pres.ladder[rung].rep_id
        init = yield from self._init(rep, rec)
        if isinstance(init, Failed):
            return (yield from self._recover(k, rung, init, rec))
        media = yield from self._get(self._request("media", k, rep, self._judge(rung, state)), rec)
        if isinstance(media, Done):
            self.samples.append(throughput_sample(keyframe, media))
            return self._chosen(k, rung, rec, media)
        self.samples.append(throughput_sample(keyframe))
        return (yield from self._recover(k, rung, media, rec))

    def _init(self, rep: str, rec: GOPRecord) -> Steps[Outcome | None]:
        """The init segment of `rep`, downloaded once (its bytes count to the GOP that needed it first);
        None when it was downloaded before."""
        if rep in self.inits:
            return None
        outcome = yield from self._get(self._request("init", rec.index, rep), rec)
        if isinstance(outcome, Done):
            self.inits[rep] = outcome.data
            rec.init_bytes += outcome.nbytes
        return outcome

    def _get(self, request: Request, rec: GOPRecord, first: Failed | None = None
             ) -> Steps[Outcome]:
        return (yield from with_retries(request, rec, self.download, self._count_retry, first))

    def _count_retry(self) -> None:
        self.retries += 1

    def _request(self, kind: str, k: int, rep: str, judge: Judge | None = None) -> Request:
        """The request for a part of GOP k: its URL and its size cap from the manifest."""
        pres = self.pres
        if kind == "keyframe":
            return Request(kind, k, rep, pres.keyframe_url(k, rep), pres.max_keyframe_bytes(rep), judge)
        if kind == "init":
            return Request(kind, k, rep, pres.init_url(rep), MAX_INIT_BYTES, judge)
        return Request(kind, k, rep, pres.media_url(rep, k), pres.max_media_bytes(rep), judge)

    def _chosen(self, k: int, rung: int, rec: GOPRecord, media: Done) -> Fetched:
        r = self.pres.ladder[rung]
        rec.rep, rec.qp, rec.feature_bytes, rec.ttfb_s = r.rep_id, r.qp, rec.feature_bytes + media.nbytes, media.ttfb
        return Fetched(k, rung, init=self.inits.get(r.rep_id), media=media.data)

    def _state(self, k: int, keyframe_bits: float, waited_s: float, round_trips: int, keyframe_fetched: bool = False,
               extra: list[ThroughputSample] | None = None) -> AbrState:
        upcoming = []
        for j in range(k, min(k + self.settings.mpc_horizon, self.pres.num_gops)):
            info = self.gop_info(j)
            if info is None:
                break
            upcoming.append(info)
        return AbrState(self.pres.abr_bandwidths(), self.pres.segment_seconds, self.buffer_level(),
                        self.capacity_s, [*self.samples, *(extra or [])], keyframe_bits,
                        upcoming[0].segment_bits if upcoming else None, self.current, round_trips=round_trips,
                        keyframe_fetched=keyframe_fetched, waited_s=waited_s, upcoming=upcoming,
                        playing=self.playing())

    # --- recovery: a keyframe the decoder rejected, features that do not decode, a feature download that failed or
    # was abandoned while it arrived; each falls back to the rung the abandonment chose or to the lowest, and a
    # failure at the lowest rung ends the playback ---

    def refetch_keyframe(self, k: int, rec: GOPRecord, reason: str, rep: str) -> Step:
        """GOP k's keyframe of Representation `rep` once more, after the decoder rejected it (damaged in transit?)."""
        rec.events.append(f"keyframe rejected, downloaded again: {reason}")
        keyframe = yield from self._keyframe(k, rec, rep)
        return Fetched(k, -1, keyframe=keyframe.data, keyframe_rep=rep)

    def fallback(self, k: int, rec: GOPRecord, rung: int, reason: str) -> Step:
        """GOP k's features at the lowest rung, after those of `rung` did not decode."""
        if rung == 0:
            raise ScheduleError(f"feature segment of GOP {k}: {reason}")
        rec.events.append(f"fallback from {rec.rep}: feature segment does not decode ({reason})")
        self._decided(rec, Decision(0, "fallback", f"{rec.rep} does not decode"))
        return (yield from self._lowest(k, rec))

    def _recover(self, k: int, rung: int, failure: Failed | Abandoned, rec: GOPRecord) -> Step:
        """After the rung's init or media failed or was abandoned: the rung the abandonment chose, else the
        lowest; a failure at the lowest rung ends the playback."""
        rep = self.pres.ladder[rung].rep_id
        target = 0
        if isinstance(failure, Abandoned):
            self.samples.append(ThroughputSample(failure.nbytes, failure.seconds, failure.ttfb))
            rec.abandoned_bytes += failure.nbytes
            self.wasted_bytes += failure.nbytes
            rec.events.append(f"abandoned {rep} after {failure.nbytes} bytes ({failure.seconds:.2f} s)")
            self._decided(rec, failure.decision)
            target = failure.decision.index
        elif rung == 0:
            raise ScheduleError(f"GOP {k}: {failure.reason}")
        else:
            rec.events.append(f"fallback from {rep}: {failure.reason}")
            self._decided(rec, Decision(0, "fallback", failure.reason))
        if target > 0:
            fetched = yield from self._plain(k, target, rec)
            if isinstance(fetched, Fetched):
                return fetched
            rec.events.append(f"fallback from {self.pres.ladder[target].rep_id}: {fetched.reason}")
        return (yield from self._lowest(k, rec))

    def _lowest(self, k: int, rec: GOPRecord) -> Step:
        fetched = yield from self._plain(k, 0, rec)
        if not isinstance(fetched, Fetched):
            raise ScheduleError(f"GOP {k}: {fetched.reason}")
        return fetched

    def _plain(self, k: int, rung: int, rec: GOPRecord) -> Steps[Fetched | Failed | Abandoned]:
        """GOP k's features at `rung` with nothing to judge: its init (if new), then its media; the failure
        where one fails."""
        rep = self.pres.ladder[rung].rep_id
        init = yield from self._init(rep, rec)
        if isinstance(init, Failed):
            return init
        media = yield from self._get(self._request("media", k, rep), rec)
        if not isinstance(media, Done):
            return media
        self.samples.append(throughput_sample(media))
        return self._chosen(k, rung, rec, media)

    def _judge(self, rung: int, state: AbrState) -> Judge | None:
        if not self.adaptive or rung == 0:
            return None

        sizes, segment_s = state.sizes(), state.segment_s

        def judge(received: int, total: int | None, elapsed_s: float, ttfb_s: float) -> Decision | None:
            flight = InFlight(rung, received, total, elapsed_s, ttfb_s)
            return self.abandon.judge(flight, sizes, self.buffer_level(), segment_s)

        return judge

    @staticmethod
    def _decided(rec: GOPRecord, decision: Decision) -> None:
        rec.decisions.append(decision.to_json())
