"""The discrete-event simulator: one playback on a virtual clock, driving the player's own fetch schedule.

The fetch policy is `stgs.client.schedule.FetchSchedule`, the one the player
drives: the same requests (keyframe, ABR decision, init once per
Representation, media judged by the abandonment rule), the same retries with
backoff, the same fallbacks to the lowest rung, the same decisions and
reasons in the log. The fetcher polls for buffer room every min(50 ms, T/20)
and playback uses the player's `PlaybackClock` (start-up, due times, stalls).
Transfers take the time `stgs.harness.network.Network` computes, faults
included; decoding takes `decode_s` per GOP, one at a time, with at most two
decoded GOPs held (the playing one and the next), as in the player. The
output has the player's log format; `not_modelled` lists what the player
does that no simulated scenario can trigger.
"""

from __future__ import annotations

import math

from stgs.client.abr import AbrSettings, make_rule
from stgs.client.clock import PlaybackClock
from stgs.client.download import RETRY_STATUS, DownloadSettings
from stgs.client.playlog import GOPRecord, playback_log
from stgs.client.schedule import (
    Abandoned,
    Done,
    Failed,
    Fetched,
    FetchSchedule,
    Outcome,
    Request,
    ScheduleError,
    Step,
    Wait,
)
from stgs.harness.ladder import Ladder
from stgs.harness.network import DELIVERY_CHUNK, Network
from stgs.harness.scenario import Scenario

MAX_POLLS = 10_000_000
"""Bound on the fetcher's waits for buffer room (a playback that never drains its buffer is a bug)."""
NOT_MODELLED = [
    "request timeouts (DownloadSettings: connect, read, total); an outage longer than the read timeout makes the "
    "player retry, the simulator waits it out",
    "keyframe re-download and feature fallback after a segment fails to decode (the simulator does not decode)",
]
"""What the player does that a simulated scenario cannot trigger."""


class Simulation:
    def __init__(self, ladder: Ladder, scenario: Scenario, rule_name: str, settings: AbrSettings | None = None,
                 download: DownloadSettings | None = None):
        self.ladder, self.sc = ladder, scenario
        self.settings = settings or AbrSettings()
        pres = ladder.pres
        rule = make_rule(rule_name, [r.qp for r in pres.ladder], scenario.qp, self.settings)
        self.T = pres.segment_seconds
        span = pres.span(scenario.start_s, scenario.duration_s, scenario.buffer_s)
        self.k0, frames, self.gops = span.first_gop, span.frames, span.gops
        self.clock = PlaybackClock(self.T, span.buffer_s, self.k0)
        self.net = Network(scenario.effects, scenario.seed)
        self.poll = min(0.05, self.T / 20)
        self.now = 0.0
        self.schedule = FetchSchedule(pres, rule, lambda: self.clock.buffer_level(self.now), span.buffer_s,
                                      lambda k: [ladder.media_bytes[r.rep_id][k] * 8 for r in pres.ladder],
                                      self.settings, download or DownloadSettings())
        self.error: str | None = None
        self.records = {k: GOPRecord(k) for k in self.gops}
        g = pres.shape.gop_size
        for k, rec in self.records.items():
            rec.presented = min(g, frames - (k - self.k0) * g)
        self.decoder_free = 0.0

    # --- playback timeline ---

    def advance(self, until: float) -> None:
        """Start every GOP whose start time has come by `until` (ready, decoded and due)."""
        while True:
            k = self.clock.playing if self.clock.t0 is None else self.clock.playing + 1
            rec = self.records.get(k)
            if rec is None or rec.fetch_end_s is None or rec.play_start_s is not None:
                return
            # decoding needs a free slot: the GOP two before has finished (the one before has started)
            slot = self.records[k - 1].play_start_s if k - 2 >= self.k0 else 0.0
            ready = max(rec.fetch_end_s, self.decoder_free, slot) + self.sc.decode_s
            start = ready if self.clock.t0 is None else max(ready, self.clock.due(k))
            if start > until:
                return
            self.decoder_free = ready
            rec.boundary_wait_s = ready if self.clock.t0 is None else 0.0
            rec.stall_s = self.clock.start(k, ready, ready if self.clock.t0 is None else self.clock.due(k))
            rec.play_start_s = self.clock.due(k)

    def wait_for_room(self) -> None:
        for _ in range(MAX_POLLS):
            self.advance(self.now)
            if self.clock.has_room(self.now):
                return
            self.now += self.poll
        raise RuntimeError(f"simulation made no progress by t = {self.now:.1f} s (buffer never drained)")

    # --- transfers: the schedule decides, this performs its requests on the virtual clock ---

    def drive(self, steps: Step, rec: GOPRecord) -> Fetched:
        outcome = None
        while True:
            try:
                item = steps.send(outcome)
            except StopIteration as stop:
                return stop.value
            if isinstance(item, Wait):
                self.now += item.seconds
                self.advance(self.now)
                outcome = None
            else:
                outcome = self.perform(item, rec)

    def perform(self, req: Request, rec: GOPRecord) -> Outcome:
        """One request: a round trip, then the body paced by the network (judged per chunk when abandonable)."""
        ladder = self.ladder
        nbytes = (ladder.keyframe_bytes[req.gop] if req.kind == "keyframe" else
                  ladder.init_bytes[req.rep] if req.kind == "init" else ladder.media_bytes[req.rep][req.gop])
        start = self.now
        rtt = self.net.round_trip()
        rec.latency_ms.append(rtt * 1e3)
        body_start = start + rtt
        status = self.net.fault(req.url)
        if status is not None:
            self.now = body_start
            self.advance(self.now)
            return Failed(f"{req.url}: HTTP {status}", retryable=status in RETRY_STATUS, seconds=self.now - start)
        end = self.net.finish(body_start, nbytes * 8)
        if req.judge is not None:
            # the player judges a download each time a chunk arrives (none arrive during an outage)
            for received in range(DELIVERY_CHUNK, nbytes, DELIVERY_CHUNK):
                self.now = self.net.finish(body_start, received * 8)
                self.advance(self.now)
                decision = req.judge(received, nbytes, self.now - start)
                if decision is not None:
                    return Abandoned(received, self.now - start, decision)
        self.now = end
        self.advance(self.now)
        return Done(nbytes, end - start, rtt)

    def fetch(self, k: int) -> None:
        rec = self.records[k]
        rec.fetch_start_s = self.now
        self.drive(self.schedule.fetch_gop(k, rec), rec)
        rec.fetch_end_s = self.now
        rec.download_s = rec.fetch_end_s - rec.fetch_start_s

    def run(self) -> dict:
        for k in self.gops:
            self.wait_for_room()
            try:
                self.fetch(k)
            except ScheduleError as exc:
                self.error = str(exc)
                break
            self.clock.fetched_end = k + 1
        self.advance(math.inf)
        return self.log()

    def log(self) -> dict:
        return playback_log([self.records[k] for k in self.gops], self.clock, url=self.ladder.url,
                            abr=self.schedule.rule.name, wasted_bytes=self.schedule.wasted_bytes,
                            retries=self.schedule.retries, error=self.error, gops_planned=len(self.gops),
                            extra={"engine": "sim", "not_modelled": NOT_MODELLED})


def simulate(ladder: Ladder, scenario: Scenario, rule: str, settings: AbrSettings | None = None) -> dict:
    """One simulated playback (the player's log format, `engine: sim`)."""
    return Simulation(ladder, scenario, rule, settings).run()
