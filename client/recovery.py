"""The fetch schedule's recovery paths (client/schedule.py's `FetchSchedule` inherits them): a keyframe the decoder
rejected, features that do not decode, and a feature download that failed or was abandoned while it arrived (the
abandonment rule's judge), each falling back to the rung the abandonment chose or to the lowest; a failure at the
lowest rung ends the playback."""

from __future__ import annotations

from collections.abc import Callable, Generator

from stgs.client.abr import AbandonRule, AbrState, Decision, InFlight, ThroughputSample
from stgs.client.fetchsteps import (
    Abandoned,
    Done,
    Failed,
    Fetched,
    Judge,
    Outcome,
    Request,
    ScheduleError,
    Step,
    Wait,
    throughput_sample,
)
from stgs.client.manifest import Presentation
from stgs.client.playlog import GOPRecord


class ScheduleRecovery:
    """What FetchSchedule does when a part of a GOP fails; it relies on the schedule's fields and request helpers."""

    pres: Presentation
    samples: list[ThroughputSample]
    wasted_bytes: int
    abandon: AbandonRule
    adaptive: bool
    buffer_level: Callable[[], float]

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

    def _plain(self, k: int, rung: int, rec: GOPRecord) -> Generator[Request | Wait, Outcome | None,
                                                                      Fetched | Failed | Abandoned]:
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
