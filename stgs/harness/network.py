"""How long a request takes under a scenario's effects (the simulator's clock and the emulator's pacing).

Only named effects apply: with none, every transfer is instant.
- bandwidth: the trace's rate (looping); outages: zero rate inside them;
- competing K: a fair share, rate / (K + 1);
- loss p: retransmissions cost a factor (1 − p) of the rate, and with a
  latency named TCP's rate is also capped by Mathis et al.'s
  1.22 · MSS / (RTT · √p);
- latency_ms: one round trip before the first byte; jitter_ms: a uniform
  ± offset on it per request (never below zero), from the scenario's seed;
- faults: matching segment requests are answered with an HTTP error (after
  the round trip), as many times as the fault says.
- concurrent requests share the link first come, first served: a response
  ready while another is still flowing starts when that one has arrived.
"""

from __future__ import annotations

import math
import random

from stgs.harness.scenario import Effects

MSS_BITS = 1460 * 8
DELIVERY_CHUNK = 16 << 10
"""Bytes that arrive at once: the emulator's proxy writes them, the player reacts to each (abandonment)."""


class Network:
    def __init__(self, effects: Effects, seed: int = 0):
        self.fx = effects
        self.rng = random.Random(seed)
        self.fault_left = [f.times for f in effects.faults or ()]
        self.link_free = 0.0
        """When the bytes already queued on the link have all arrived."""

    def fault(self, path: str) -> int | None:
        """The HTTP error status a request for `path` gets (counting it against its fault), or None."""
        for i, f in enumerate(self.fx.faults or ()):
            left = self.fault_left[i]
            if f.path in path and left != 0:
                if left is not None:
                    self.fault_left[i] = left - 1
                return f.status
        return None

    def rate(self, t: float) -> tuple[float, float]:
        """(bit/s, seconds the rate holds) at time t; math.inf bit/s without a bandwidth effect."""
        fx = self.fx
        if fx.bandwidth is None:
            bps, hold = math.inf, math.inf
        else:
            kbps, hold = fx.bandwidth.segment(t)
            bps = kbps * 1e3
        for start, end in fx.outages or ():
            if start <= t < end:
                return 0.0, end - t
            if t < start:
                hold = min(hold, start - t)
        if fx.competing:
            bps /= fx.competing + 1
        if fx.loss:
            bps *= 1 - fx.loss
            if fx.latency_ms:
                bps = min(bps, 1.22 * MSS_BITS / (fx.latency_ms / 1e3 * math.sqrt(fx.loss)))
        return bps, hold

    def round_trip(self) -> float:
        """Seconds before the first byte of a request (draws the jitter)."""
        rtt = (self.fx.latency_ms or 0.0) / 1e3
        if self.fx.jitter_ms:
            rtt += self.rng.uniform(-1, 1) * self.fx.jitter_ms / 1e3
        return max(rtt, 0.0)

    def finish(self, t: float, bits: float) -> float:
        """When `bits` sent from time t have all arrived."""
        while bits > 1e-9:
            bps, hold = self.rate(t)
            if math.isinf(bps):
                return t
            if bps > 0 and bits <= bps * hold:
                return t + bits / bps
            if math.isinf(hold):
                raise ValueError("the network never delivers these bytes (zero bandwidth forever)")
            bits -= bps * hold
            t += hold
        return t

    def queue(self, ready: float, bits: float) -> float:
        """When a response of `bits` ready at `ready` starts to flow (after those queued before it)."""
        start = max(ready, self.link_free)
        self.link_free = self.finish(start, bits)
        return start

    def release(self, t: float) -> None:
        """A transfer was dropped at time t: nothing it had left occupies the link."""
        self.link_free = min(self.link_free, t)

    def delivered(self, t: float, until: float) -> float:
        """Bits that arrive between t and until."""
        bits = 0.0
        while t < until:
            bps, hold = self.rate(t)
            step = min(hold, until - t)
            if math.isinf(bps):
                return math.inf
            bits += bps * step
            t += step
        return bits
