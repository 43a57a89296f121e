"""The discrete-event simulator: one playback on a virtual clock, driving the player's own fetch schedule.

The fetch policy is `stgs.client.fetch.schedule.FetchSchedule`, the one the player
drives: the same requests (keyframe, ABR decision, init once per
Representation, media judged by the abandonment rule), the same retries with
backoff, the same fallbacks to the lowest rung, the same decisions and
reasons in the log. The fetcher polls for buffer room every min(50 ms, T/20)
and playback uses the player's `PlaybackClock` (start-up, due times, stalls).
Transfers take the time `stgs.harness.network.Network` computes, faults
included; decoding follows the player's pipeline (stgs.harness.decode: keyframes whole, feature frames one by
one into a bounded ring, frames dropped when their features are late), with at most two decoded GOPs held
(the playing one and the next), at the costs the scenario's [decode] table gives. A layered scene's
static layer is fetched first, once, through the same schedule, and decoded (`static_ms`) before the
first GOP's features. The output has the player's log format; `not_modelled` lists what the player
does that no simulated scenario can trigger.
"""

from __future__ import annotations

import math
from typing import TypeVar

from stgs.client.abr import AbrSettings, make_rule
from stgs.client.clock import PlaybackClock
from stgs.client.fetch.download import RETRY_STATUS, DownloadSettings
from stgs.client.fetch.schedule import FetchSchedule
from stgs.client.fetch.steps import (
    Abandoned,
    Done,
    Failed,
    Outcome,
    Parallel,
    Request,
    ScheduleError,
    Steps,
    Wait,
)
from stgs.client.playlog import GOPRecord, playback_log
from stgs.errors import StgsError
from stgs.harness.decode import DecoderModel
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

T = TypeVar("T")



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
                                      ladder.gop_info, self.settings, download or DownloadSettings(),
                                      clock=lambda: self.now, playing=lambda: self.clock.t0 is not None)
        self.error: str | None = None
        self.static_ready = 0.0
        """When the static layer is decoded (format 2; 0 in format 1)."""
        self.records = {k: GOPRecord(k) for k in self.gops}
        g = pres.shape.gop_size
        for k, rec in self.records.items():
            rec.presented = min(g, frames - (k - self.k0) * g)
        self.decoder = DecoderModel(scenario.decode.ring_frames, pres.shape.window, g, pres.fps,
                                    scenario.decode.render_ahead)
        self.lead = scenario.decode.render_ahead / pres.fps
        """The renderer's head start at the first GOP and after a stall (stgs.client.framepath)."""
        if scenario.decode.ring_frames < pres.shape.window:
            raise StgsError(f"{scenario.name}: a ring of {scenario.decode.ring_frames} feature frames cannot hold "
                            f"one frame's window of {pres.shape.window}")

    def decode_costs(self, k: int, rec: GOPRecord) -> tuple[float, float]:
        """(keyframe, feature frame) decode seconds of GOP k at the rung it was fetched at."""
        return self.sc.decode.keyframe_ms / 1e3, self.sc.decode.frame_s(rec.rep)

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
            assert slot is not None  # the GOP before has started
            keyframe_s, frame_s = self.decode_costs(k, rec)
            plan = self.decoder.plan(rec.fetch_end_s, slot, keyframe_s, frame_s, self.static_ready)
            ready = plan.ready
            arrived = ready if self.clock.t0 is None else self.clock.due(k)
            if self.clock.start_time(k, ready, arrived, self.lead) > until:
                return
            rec.boundary_wait_s = ready if self.clock.t0 is None else 0.0
            rec.stall_s = self.clock.start(k, ready, arrived, self.lead)
            rec.play_start_s = self.clock.due(k)
            rec.dropped = min(rec.presented, self.decoder.start(plan, rec.play_start_s))
            rec.keyframe_decode_s, rec.feature_decode_s = keyframe_s, frame_s * self.decoder.features

    def wait_for_room(self) -> None:
        for _ in range(MAX_POLLS):
            self.advance(self.now)
            if self.clock.has_room(self.now):
                return
            self.now += self.poll
        raise RuntimeError(f"simulation made no progress by t = {self.now:.1f} s (buffer never drained)")

    # --- transfers: the schedule decides, this performs its requests on the virtual clock ---

    def drive(self, steps: Steps[T], rec: GOPRecord) -> T:
        outcome: Outcome | tuple[Outcome, ...] | None = None
        while True:
            try:
                item = steps.send(outcome)
            except StopIteration as stop:
                return stop.value
            if isinstance(item, Wait):
                self.now += item.seconds
                self.advance(self.now)
                outcome = None
            elif isinstance(item, Parallel):
                outcome = self.perform_all(item.requests, rec)
            else:
                outcome = self.perform(item, rec, self.now, self.round_trip(rec))

    def round_trip(self, rec: GOPRecord) -> float:
        rtt = self.net.round_trip()
        rec.latency_ms.append(rtt * 1e3)
        return rtt

    def perform_all(self, requests: tuple[Request, ...], rec: GOPRecord) -> tuple[Outcome, ...]:
        """Requests sent at once: each after its own round trip, their bodies sharing the link in arrival order."""
        start = self.now
        rtts = [self.round_trip(rec) for _ in requests]
        outcomes = {i: self.perform(requests[i], rec, start, rtts[i])
                    for i in sorted(range(len(requests)), key=lambda i: rtts[i])}
        return tuple(outcomes[i] for i in range(len(requests)))

    def perform(self, req: Request, rec: GOPRecord, start: float, rtt: float) -> Outcome:
        """One request sent at `start`: a round trip, then the body paced by the network once the link is free
        (judged per chunk when abandonable)."""
        ladder = self.ladder
        nbytes = (ladder.keyframe_size(req.rep, req.gop) if req.kind == "keyframe" else
                  ladder.init_bytes[req.rep] if req.kind == "init" else
                  ladder.static_bytes if req.kind == "static" else ladder.media_bytes[req.rep][req.gop])
        ready = start + rtt
        status = self.net.fault(req.url)
        if status is not None:
            self.now = max(self.now, ready)
            self.advance(self.now)
            return Failed(f"{req.url}: HTTP {status}", retryable=status in RETRY_STATUS, seconds=ready - start)
        body_start = self.net.queue(ready, nbytes * 8)
        end = self.net.link_free
        if req.judge is not None:
            # the player judges a download each time a chunk arrives (none arrive during an outage)
            t = body_start
            for received in range(DELIVERY_CHUNK, nbytes, DELIVERY_CHUNK):
                t = self.net.finish(t, DELIVERY_CHUNK * 8)  # the same integral as from body_start, piece by piece
                self.now = max(self.now, t)
                self.advance(self.now)
                decision = req.judge(received, nbytes, t - start, body_start - start)
                if decision is not None:
                    self.net.release(t)
                    return Abandoned(received, t - start, decision, body_start - start)
        self.now = max(self.now, end)
        self.advance(self.now)
        return Done(nbytes, end - start, body_start - start)

    def fetch(self, k: int) -> None:
        rec = self.records[k]
        rec.fetch_start_s = self.now
        self.drive(self.schedule.fetch_gop(k, rec), rec)
        rec.fetch_end_s = self.now
        rec.download_s = rec.fetch_end_s - rec.fetch_start_s

    def fetch_static(self) -> None:
        """The static layer before the first GOP (format 2), then its decode."""
        rec = self.records[self.k0]
        self.drive(self.schedule.fetch_static(rec), rec)
        rec.static_decode_s = self.sc.decode.static_ms / 1e3
        self.static_ready = self.now + rec.static_decode_s

    def run(self) -> dict:
        if self.ladder.pres.static is not None:
            try:
                self.fetch_static()
            except ScheduleError as exc:
                self.error = str(exc)
                return self.log()
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
