"""The classic rules (web/src/abr/rules.ts is their port): throughput, BOLA, BOLA-E, insufficient-buffer,
DYNAMIC (the collection dash.js runs by default) and a pinned rung; stgs.client.abr's docstring says what each does."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from stgs.client.abr.state import (
    AbrSettings,
    AbrState,
    Decision,
    throughput_kbps,
)


def highest_fitting(state: AbrState, kbps: float, seconds: float, bits: list[float] | None = None) -> int:
    """The highest rung whose keyframe + features (`bits` per rung; default the next GOP's own) arrive within
    `seconds` at `kbps` after the round trips (0 when none does)."""
    budget = kbps * 1e3 * (seconds - state.latency_s())
    best = 0
    for i, b in enumerate(bits if bits is not None else [state.keyframe_bits + s for s in state.sizes()]):
        if b <= budget:
            best = i
    return best


@dataclass
class ThroughputRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "throughput"

    def choose(self, state: AbrState) -> Decision:
        s = self.settings
        kbps = throughput_kbps(state.samples, s)
        if kbps is None:
            return Decision(0, self.name, "no throughput sample yet: lowest rung")
        T, latency = state.segment_s, state.latency_s()
        spend = kbps * s.safety_factor
        sustained = state.sustained_bits(s.sustained_gops)
        best = highest_fitting(state, spend, T, sustained)
        held = ""
        held_at = state.current or 0  # from the lowest rung at start-up
        if best > held_at:
            up = highest_fitting(state, spend * (1 - s.switch_up_headroom), T, sustained)
            if up < best:
                best, held = max(up, held_at), f" (up needs {s.switch_up_headroom:g} of the budget to spare)"
        budget = spend * (T - latency) / T
        rtt = f" after {latency * 1e3:.0f} ms of round trips" if latency else ""
        return Decision(best, self.name, f"estimate {kbps:.0f} kbit/s x {s.safety_factor:g} = budget {budget:.0f} "
                        f"kbit/s{rtt}; rung {best} sustains {sustained[best] / T / 1e3:.0f}{held}")


@dataclass
class BolaRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "bola"

    def parameters(self, state: AbrState) -> tuple[list[float], list[float], float, float]:
        """(sizes, utilities, V, γp) for this state, on each rung's sustained size (AbrSettings.sustained_gops)."""
        sizes = state.sustained_bits(self.settings.sustained_gops)
        utilities = [math.log(s / sizes[0]) + 1 for s in sizes]
        min_buffer = self.settings.bola_min_buffer_s or state.segment_s
        # decisions happen at buffer <= capacity - T (a GOP must fit): a target above that is never reached
        target = max(state.buffer_capacity_s - state.segment_s, min_buffer + state.segment_s)
        gp = max(utilities[-1] - 1, 1e-9) / (target / min_buffer - 1)
        return sizes, utilities, min_buffer / gp, gp

    def best_at(self, state: AbrState, buffer_s: float) -> tuple[int, float]:
        """(rung, its score per bit) at a buffer level."""
        sizes, utilities, v, gp = self.parameters(state)
        scores = [(v * (u + gp) - buffer_s) / s for u, s in zip(utilities, sizes, strict=True)]
        best = max(range(len(scores)), key=lambda i: (scores[i], i))
        return best, scores[best]

    def thresholds(self, state: AbrState, rung: int) -> tuple[float, float]:
        """The buffer levels between which BOLA picks `rung` (dash.js's min/maxBufferLevelForQuality)."""
        sizes, utilities, v, gp = self.parameters(state)

        def crossing(lo: int, hi: int) -> float:  # buffer above which `hi` scores at least `lo`
            return v * ((utilities[lo] + gp) * sizes[hi] - (utilities[hi] + gp) * sizes[lo]) / (sizes[hi] - sizes[lo])

        low = max((crossing(i, rung) for i in range(rung) if sizes[i] < sizes[rung]), default=0.0)
        high = min((crossing(rung, i) for i in range(rung + 1, len(sizes)) if sizes[i] > sizes[rung]),
                   default=math.inf)
        return max(low, 0.0), high

    def choose(self, state: AbrState) -> Decision:
        _, _, v, gp = self.parameters(state)
        best, score = self.best_at(state, state.buffer_s)
        return Decision(best, self.name, f"buffer {state.buffer_s:.2f} s, V {v:.3g}, gamma*p {gp:.3g}: "
                        f"best score {score:.3g} per bit")


@dataclass
class BolaERule:
    """BOLA-E (Spiteri, Sitaraman, Sparacio 2019) as dash.js runs it; see the module docstring."""

    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "bola-e"
    placeholder_s: float = 0.0
    """Virtual buffer added to the real one."""
    steady: bool = False
    """Past start-up (the buffer has held a whole GOP)."""
    last: int | None = None

    def __post_init__(self) -> None:
        self.bola = BolaRule(self.settings)
        self.throughput = ThroughputRule(self.settings)

    def choose(self, state: AbrState) -> Decision:
        T = state.segment_s
        tp = self.throughput.choose(state).index
        if self.steady and state.playing and state.buffer_s <= 1e-9:
            self.steady, self.placeholder_s = False, 0.0  # a stall: start over
        if not self.steady:
            rung = tp
            self.placeholder_s = max(0.0, self.bola.thresholds(state, rung)[0] - state.buffer_s)
            self.steady = state.buffer_s >= T
            reason = (f"start-up: throughput's rung {rung}; placeholder {self.placeholder_s:.2f} s so BOLA agrees")
        else:
            self.placeholder_s += state.waited_s
            virtual = state.buffer_s + self.placeholder_s
            rung, _ = self.bola.best_at(state, virtual)
            reason = f"buffer {state.buffer_s:.2f} + placeholder {self.placeholder_s:.2f} s: BOLA's rung {rung}"
            if self.last is not None and rung > self.last and rung > tp:
                rung = max(tp, self.last)
                reason += f", held at {rung} (BOLA-O: above what the throughput sustains)"
            excess = virtual - self.bola.thresholds(state, rung)[1]
            if excess > 0:
                self.placeholder_s = max(0.0, self.placeholder_s - excess)
        self.last = rung
        return Decision(rung, self.name, reason)


@dataclass
class InsufficientBufferRule:
    """Cap: a GOP of the sustained size must download within `insufficient_buffer_safety` x buffer at the estimate
    (only once playing, and only with a sample)."""

    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "insufficient-buffer"

    def choose(self, state: AbrState) -> Decision | None:
        kbps = throughput_kbps(state.samples, self.settings)
        if kbps is None or not state.playing:
            return None
        window = state.buffer_s * self.settings.insufficient_buffer_safety
        cap = highest_fitting(state, kbps, window, state.sustained_bits(self.settings.sustained_gops))
        return Decision(cap, self.name, f"buffer {state.buffer_s:.2f} s: rung {cap} is the highest that arrives in "
                        f"{window:.2f} s at {kbps:.0f} kbit/s")


@dataclass
class DynamicRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "dynamic"
    using_bola: bool = False
    """Which rule decided last (hysteresis state)."""

    def __post_init__(self) -> None:
        self.throughput = ThroughputRule(self.settings)
        self.bola = BolaERule(self.settings)
        self.insufficient = InsufficientBufferRule(self.settings)

    def choose(self, state: AbrState) -> Decision:
        s = self.settings
        if self.using_bola and state.buffer_s < s.dynamic_bola_off * state.buffer_capacity_s:
            self.using_bola = False
        elif not self.using_bola and state.buffer_s >= s.dynamic_bola_on * state.buffer_capacity_s:
            self.using_bola = True
        throughput = self.throughput.choose(state)
        bola = self.bola.choose(state)  # every GOP, so its placeholder follows the buffer
        band = (f">= {s.dynamic_bola_off:g}" if self.using_bola else f"< {s.dynamic_bola_on:g}")
        where = f"dynamic: buffer {state.buffer_s:.2f} s {band} x capacity {state.buffer_capacity_s:.2f} s"
        if not self.using_bola:
            chosen = Decision(throughput.index, throughput.rule, f"{where}; {throughput.reason}")
        elif bola.index < throughput.index:
            chosen = Decision(throughput.index, throughput.rule, f"{where}, but bola's rung {bola.index} is below "
                              f"throughput's; {throughput.reason}")
        else:
            chosen = Decision(bola.index, bola.rule, f"{where}; {bola.reason}")
        cap = self.insufficient.choose(state)
        if cap is not None and cap.index < chosen.index:
            return Decision(cap.index, cap.rule, f"{chosen.reason}; capped: {cap.reason}")
        return chosen


@dataclass
class FixedRule:
    index: int
    name: str = "fixed"

    def choose(self, state: AbrState) -> Decision:
        return Decision(self.index, self.name, f"pinned rung {self.index}")
