"""The discrete-event simulator: one playback on a virtual clock, with the player's own ABR rules and clock.

It follows `stgs.client.player.Session` step for step: the fetcher polls for
buffer room every min(50 ms, T/20), downloads GOP k's keyframe, asks the ABR
rule with the same `AbrState` (the keyframe's exact size, the next segment's
sizes from the ladder, the throughput history), downloads the init segment
once per Representation and the media segment (abandoning it to the lowest
rung exactly when the player would), and playback uses the same
`PlaybackClock` (start-up, due times, stalls). Transfers take the time
`stgs.harness.network.Network` computes; decoding takes `decode_s` per GOP,
one at a time, with at most two decoded GOPs held (the playing one and the
next), as in the player. The output has the player's log format.
"""

from __future__ import annotations

import math

from stgs.client.abr import (
    AbrSettings,
    AbrState,
    FixedRule,
    ThroughputSample,
    deciding_rule,
    make_rule,
    should_abandon,
    throughput_kbps,
)
from stgs.client.clock import PlaybackClock
from stgs.client.playlog import GOPRecord, playback_log
from stgs.harness.ladder import Ladder
from stgs.harness.network import DELIVERY_CHUNK, Network
from stgs.harness.scenario import Scenario

MAX_POLLS = 10_000_000
"""Bound on the fetcher's waits for buffer room (a playback that never drains its buffer is a bug)."""


class Simulation:
    def __init__(self, ladder: Ladder, scenario: Scenario, rule_name: str, settings: AbrSettings | None = None):
        self.ladder, self.sc = ladder, scenario
        self.settings = settings or AbrSettings()
        pres = ladder.pres
        self.rule = make_rule(rule_name, [r.qp for r in pres.ladder], scenario.qp, self.settings, option="qp")
        self.T = pres.segment_seconds
        span = pres.span(scenario.start_s, scenario.duration_s, scenario.buffer_s)
        self.k0, frames, self.gops = span.first_gop, span.frames, span.gops
        self.clock = PlaybackClock(self.T, span.buffer_s, self.k0)
        self.net = Network(scenario.effects, scenario.seed)
        self.poll = min(0.05, self.T / 20)
        self.now = 0.0
        self.samples: list[ThroughputSample] = []
        self.records = {k: GOPRecord(k) for k in self.gops}
        g = pres.shape.gop_size
        for k, rec in self.records.items():
            rec.presented = min(g, frames - (k - self.k0) * g)
        self.inits: set[str] = set()
        self.decoder_free = 0.0
        self.wasted = 0

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

    # --- transfers ---

    def transfer(self, nbytes: int, rec: GOPRecord, adaptive_check=None) -> tuple[float, int, bool]:
        """Advance the clock over one request; returns (seconds, bytes received, abandoned)."""
        start = self.now
        rtt = self.net.round_trip()
        rec.latency_ms.append(rtt * 1e3)
        body_start = start + rtt
        end = self.net.finish(body_start, nbytes * 8)
        if adaptive_check is not None:
            # the player judges a download each time a chunk arrives (none arrive during an outage)
            for received in range(DELIVERY_CHUNK, nbytes, DELIVERY_CHUNK):
                t = self.net.finish(body_start, received * 8)
                self.advance(t)
                if adaptive_check(received, nbytes, t - start, self.clock.buffer_level(t)):
                    self.now = t
                    return t - start, received, True
        self.now = end
        return end - start, nbytes, False

    def fetch(self, k: int, current: int | None) -> int:
        rec = self.records[k]
        rec.fetch_start_s = self.now
        kf = self.ladder.keyframe_bytes[k]
        seconds, _, _ = self.transfer(kf, rec)
        self.samples.append(ThroughputSample(kf, seconds))
        self.advance(self.now)
        ladder = self.ladder.pres.ladder
        sizes = [self.ladder.media_bytes[r.rep_id][k] * 8 for r in ladder]
        state = AbrState([r.bandwidth for r in ladder], self.T, self.clock.buffer_level(self.now),
                         self.clock.capacity_s, list(self.samples), kf * 8, sizes, current)
        rung = self.rule.choose(state)
        rec.rule = deciding_rule(self.rule)
        rec.buffer_s, rec.estimate_kbps = state.buffer_s, throughput_kbps(state.samples, self.settings)
        rec.keyframe_bytes = kf
        rung = self.fetch_media(k, rung, rec, sizes[0] / 8)
        rec.fetch_end_s = self.now
        rec.download_s = rec.fetch_end_s - rec.fetch_start_s
        return rung

    def fetch_media(self, k: int, rung: int, rec: GOPRecord, lowest_bytes: float) -> int:
        rep = self.ladder.pres.ladder[rung].rep_id
        self.fetch_init(rep, rec)
        size = self.ladder.media_bytes[rep][k]
        check = None
        if not isinstance(self.rule, FixedRule) and rung > 0:
            def check(received: int, total: int, elapsed: float, buffer_s: float) -> bool:
                return should_abandon(received, total, elapsed, buffer_s, lowest_bytes, self.settings)
        seconds, received, abandoned = self.transfer(size, rec, check)
        self.samples.append(ThroughputSample(received, seconds))
        if not abandoned:
            rec.rep, rec.qp, rec.feature_bytes = rep, self.ladder.pres.ladder[rung].qp, size
            return rung
        rec.abandoned_bytes += received
        self.wasted += received
        rec.events.append(f"abandoned {rep} after {received} bytes ({seconds:.2f} s)")
        low = self.ladder.pres.ladder[0].rep_id
        self.fetch_init(low, rec)
        size = self.ladder.media_bytes[low][k]
        seconds, _, _ = self.transfer(size, rec)
        self.samples.append(ThroughputSample(size, seconds))
        rec.rep, rec.qp, rec.feature_bytes = low, self.ladder.pres.ladder[0].qp, size
        return 0

    def fetch_init(self, rep: str, rec: GOPRecord) -> None:
        if rep in self.inits:
            return
        self.inits.add(rep)
        rec.init_bytes += self.ladder.init_bytes[rep]
        self.transfer(self.ladder.init_bytes[rep], rec)

    def run(self) -> dict:
        current = None
        for k in self.gops:
            self.wait_for_room()
            current = self.fetch(k, current)
            self.clock.fetched_end = k + 1
        self.advance(math.inf)
        return self.log()

    def log(self) -> dict:
        return playback_log([self.records[k] for k in self.gops], self.clock, url=self.ladder.url,
                            abr=self.rule.name, wasted_bytes=self.wasted, retries=0, error=None,
                            gops_planned=len(self.gops), extra={"engine": "sim"})


def simulate(ladder: Ladder, scenario: Scenario, rule: str, settings: AbrSettings | None = None) -> dict:
    """One simulated playback (the player's log format, `engine: sim`)."""
    return Simulation(ladder, scenario, rule, settings).run()
