"""Adaptive bitrate rules: small objects behind one interface, defaults in one settings place.

A rule gets an `AbrState` (ladder, throughput history, buffer level, the
next GOP's keyframe and per-Representation segment sizes, and for a download
in flight its progress) and returns a `Decision`: the ladder rung, the rule
that decided and the reason with the numbers it used (dash.js's
SwitchRequest). The playback log keeps every decision. The keyframe part of
every GOP is not adaptive: each rule counts its bits before it spends
anything on features.

- `ThroughputRule`: EWMA throughput with a fast and a slow half-life (the
  lower of the two, as dash.js does), times a safety factor, minus the
  keyframe's bit rate; the highest rung whose next segment fits.
- `BolaRule`: BOLA (Spiteri et al., buffer-based Lyapunov optimisation, as
  in dash.js's BolaRule): utility v_m = ln(size_m / size_0) + 1 of the whole
  GOP (keyframe + features); choose argmax (V·(v_m + γp) − buffer) / size_m.
  Its target buffer is the highest level a decision is ever made at
  (capacity − one GOP: the fetcher asks only when a whole GOP fits), so the
  top rung is reachable.
- `DynamicRule`: throughput while the buffer is low, BOLA once it is
  full enough (with hysteresis) and only while BOLA's choice is at least
  the throughput rule's (dash.js's DYNAMIC strategy).
- `FixedRule`: one pinned Representation (`qp`).
- `AbandonRule`: judges a feature download in flight; drops it for the
  lowest rung when it would outlast the buffer (None: no change).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

from stgs.errors import FieldError


@dataclass
class AbrSettings:
    """Every ABR default, in one place."""

    safety_factor: float = 0.9
    """Fraction of the throughput estimate the throughput rule may spend."""
    fast_half_life_s: float = 3.0
    """Half-life (seconds of download time) of the fast EWMA."""
    slow_half_life_s: float = 8.0
    """Half-life of the slow EWMA."""
    bola_min_buffer_s: float | None = None
    """BOLA's minimum buffer (None: one segment)."""
    dynamic_bola_on: float = 0.6
    """DYNAMIC switches to BOLA when the buffer reaches this fraction of its capacity."""
    dynamic_bola_off: float = 0.3
    """... and back to throughput when it falls below this fraction."""
    abandon_min_s: float = 0.2
    """A feature download is never abandoned before it has run this long."""


@dataclass(frozen=True)
class ThroughputSample:
    bytes: int
    seconds: float


@dataclass(frozen=True)
class Decision:
    """What a rule decided: a ladder rung, who decided it and why (dash.js's SwitchRequest)."""

    index: int
    """Ladder rung (0: lowest)."""
    rule: str
    """The rule that decided (DYNAMIC: the one of its two it used)."""
    reason: str
    """The numbers the rule used, in words."""

    def to_json(self) -> dict:
        return {"index": self.index, "rule": self.rule, "reason": self.reason}


@dataclass(frozen=True)
class InFlight:
    """A feature download in progress, for the abandonment rule."""

    rung: int
    received: int
    """Bytes so far."""
    total: int | None
    """Content-Length (None: unknown)."""
    elapsed_s: float
    """Media seconds since the request started."""


@dataclass
class AbrState:
    """What a rule sees when it decides the next GOP's feature Representation."""

    bandwidths: Sequence[int]
    """@bandwidth of each ladder rung (bit/s), ascending."""
    segment_s: float
    """Duration of one GOP."""
    buffer_s: float
    """Media seconds downloaded ahead of the playhead."""
    buffer_capacity_s: float
    """Most media seconds the player buffers."""
    samples: Sequence[ThroughputSample] = ()
    """Throughput history of segment downloads, oldest first."""
    keyframe_bits: float = 0.0
    """Size of the next GOP's keyframe segment."""
    segment_bits: Sequence[float] | None = None
    """Size of the next GOP's media segment per rung (None: @bandwidth x duration)."""
    current: int | None = None
    """Rung chosen for the previous GOP."""
    in_flight: InFlight | None = None
    """The feature download being judged (AbandonRule only)."""

    def sizes(self) -> list[float]:
        """Feature bits of the next GOP per rung."""
        if self.segment_bits is not None:
            return [float(b) for b in self.segment_bits]
        return [b * self.segment_s for b in self.bandwidths]


class AbrRule(Protocol):
    name: str

    def choose(self, state: AbrState) -> Decision | None:
        """The rung for the next GOP (None: no change, which only AbandonRule answers)."""


def ewma_kbps(samples: Sequence[ThroughputSample], half_life_s: float) -> float | None:
    """Duration-weighted EWMA of sample throughputs (kbit/s), zero-bias corrected; None without samples."""
    estimate, weight = 0.0, 0.0
    for s in samples:
        seconds = max(s.seconds, 1e-6)
        alpha = 0.5 ** (seconds / half_life_s)
        estimate = alpha * estimate + (1 - alpha) * (s.bytes * 8 / 1e3 / seconds)
        weight += seconds
    if weight == 0:
        return None
    return estimate / (1 - 0.5 ** (weight / half_life_s))


def throughput_kbps(samples: Sequence[ThroughputSample], settings: AbrSettings) -> float | None:
    """The estimate the throughput rule uses: the lower of the fast and slow EWMAs."""
    fast = ewma_kbps(samples, settings.fast_half_life_s)
    slow = ewma_kbps(samples, settings.slow_half_life_s)
    return None if fast is None else min(fast, slow)


@dataclass
class ThroughputRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "throughput"

    def choose(self, state: AbrState) -> Decision:
        kbps = throughput_kbps(state.samples, self.settings)
        if kbps is None:
            return Decision(0, self.name, "no throughput sample yet: lowest rung")
        budget = kbps * 1e3 * self.settings.safety_factor - state.keyframe_bits / state.segment_s
        sizes = state.sizes()
        best = 0
        for i, bits in enumerate(sizes):
            if bits / state.segment_s <= budget:
                best = i
        return Decision(best, self.name, f"estimate {kbps:.0f} kbit/s x {self.settings.safety_factor:g} - keyframe "
                        f"{state.keyframe_bits / state.segment_s / 1e3:.0f} = budget {budget / 1e3:.0f} kbit/s; "
                        f"rung {best} needs "
                        f"{sizes[best] / state.segment_s / 1e3:.0f}")


@dataclass
class BolaRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "bola"

    def parameters(self, state: AbrState) -> tuple[list[float], list[float], float, float]:
        """(sizes, utilities, V, γp) for this state."""
        sizes = [state.keyframe_bits + b for b in state.sizes()]
        utilities = [math.log(s / sizes[0]) + 1 for s in sizes]
        min_buffer = self.settings.bola_min_buffer_s or state.segment_s
        # decisions happen at buffer <= capacity - T (a GOP must fit): a target above that is never reached
        target = max(state.buffer_capacity_s - state.segment_s, min_buffer + state.segment_s)
        gp = max(utilities[-1] - 1, 1e-9) / (target / min_buffer - 1)
        return sizes, utilities, min_buffer / gp, gp

    def choose(self, state: AbrState) -> Decision:
        sizes, utilities, v, gp = self.parameters(state)
        scores = [(v * (u + gp) - state.buffer_s) / s for u, s in zip(utilities, sizes, strict=True)]
        best = max(range(len(scores)), key=lambda i: (scores[i], i))
        return Decision(best, self.name, f"buffer {state.buffer_s:.2f} s, V {v:.3g}, gamma*p {gp:.3g}: "
                        f"best score {scores[best]:.3g} per bit")


@dataclass
class DynamicRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "dynamic"
    using_bola: bool = False
    """Which rule decided last (hysteresis state)."""

    def __post_init__(self) -> None:
        self.throughput = ThroughputRule(self.settings)
        self.bola = BolaRule(self.settings)

    def choose(self, state: AbrState) -> Decision:
        s = self.settings
        if self.using_bola and state.buffer_s < s.dynamic_bola_off * state.buffer_capacity_s:
            self.using_bola = False
        elif not self.using_bola and state.buffer_s >= s.dynamic_bola_on * state.buffer_capacity_s:
            self.using_bola = True
        throughput = self.throughput.choose(state)
        band = (f">= {s.dynamic_bola_off:g}" if self.using_bola else f"< {s.dynamic_bola_on:g}")
        where = f"dynamic: buffer {state.buffer_s:.2f} s {band} x capacity {state.buffer_capacity_s:.2f} s"
        if not self.using_bola:
            return Decision(throughput.index, throughput.rule, f"{where}; {throughput.reason}")
        bola = self.bola.choose(state)
        if bola.index < throughput.index:
            return Decision(throughput.index, throughput.rule, f"{where}, but bola's rung {bola.index} is below "
                            f"throughput's; {throughput.reason}")
        return Decision(bola.index, bola.rule, f"{where}; {bola.reason}")


@dataclass
class FixedRule:
    index: int
    name: str = "fixed"

    def choose(self, state: AbrState) -> Decision:
        return Decision(self.index, self.name, f"pinned rung {self.index}")


@dataclass
class AbandonRule:
    """Drop an in-flight feature download that would outlast the buffer when restarting at the lowest rung
    would not (dash.js's AbandonRequestsRule, in spirit)."""

    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "abandon"

    def choose(self, state: AbrState) -> Decision | None:
        f = state.in_flight
        if f is None or f.rung == 0:
            return None
        lowest_bytes = state.sizes()[0] / 8
        if not should_abandon(f.received, f.total, f.elapsed_s, state.buffer_s, lowest_bytes, self.settings):
            return None
        rate = f.received / f.elapsed_s
        return Decision(0, self.name, f"{(f.total - f.received) / rate:.2f} s left at {rate * 8 / 1e3:.0f} kbit/s "
                        f"> buffer {state.buffer_s:.2f} s; the lowest rung takes {lowest_bytes / rate:.2f} s")


RULES = {"throughput": ThroughputRule, "bola": BolaRule, "dynamic": DynamicRule}
"""`--abr` names."""


def make_rule(name: str, ladder_qps: Sequence[int | None], qp: int | None, settings: AbrSettings) -> AbrRule:
    """The rule `name`, or a FixedRule on the rung of `qp` when one is pinned."""
    if qp is None:
        return RULES[name](settings)
    if qp not in ladder_qps:
        raise FieldError("qp", f"{qp} is not offered: the scene has QPs {', '.join(str(q) for q in ladder_qps)}")
    return FixedRule(list(ladder_qps).index(qp))


def should_abandon(received: int, total: int | None, elapsed_s: float, buffer_s: float, lowest_bytes: float,
                   settings: AbrSettings) -> bool:
    """Drop an in-flight feature download that would outlast the buffer when restarting at the lowest rung
    would not (dash.js's AbandonRequestsRule, in spirit)."""
    if total is None or elapsed_s < settings.abandon_min_s or received >= total or received == 0:
        return False
    rate = received / elapsed_s
    remaining_s = (total - received) / rate
    return remaining_s > buffer_s and lowest_bytes / rate < remaining_s
