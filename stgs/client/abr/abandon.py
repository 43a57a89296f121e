"""The abandonment rule: judges a feature download while it arrives (dash.js's AbandonRequestsRule, in spirit).

A download is dropped only when all of these hold, measured on its body
(bytes since the first byte; the round trip is latency, not bandwidth):
- its body has arrived for at least `abandon_min_s`;
- at the observed rate the whole transfer takes longer than one GOP (the rung
  cannot keep up with playback);
- what is left would outlast the buffer (a stall, or start-up, is coming);
- restarting lower (one more round trip plus the lower segment at the same
  rate) finishes sooner than going on.
It restarts at the highest lower rung that the observed rate sustains (its
download fits in a GOP with the safety factor), else at the lowest.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from stgs.client.abr.state import AbrSettings, AbrState, Decision, InFlight


def abandon_target(flight: InFlight, sizes: list[float], buffer_s: float, segment_s: float,
                   settings: AbrSettings) -> tuple[int, float, float] | None:
    """(rung to restart at, seconds left going on, seconds the restart takes), or None to go on."""
    f = flight
    if f.rung == 0 or f.total is None or f.received <= 0 or f.received >= f.total:
        return None
    body_s = f.elapsed_s - f.ttfb_s
    if body_s < settings.abandon_min_s:
        return None
    rate = f.received * 8 / body_s
    remaining_s = (f.total - f.received) * 8 / rate
    if f.elapsed_s + remaining_s <= segment_s or remaining_s <= buffer_s:
        return None
    restart = [f.ttfb_s + sizes[j] / rate for j in range(f.rung)]
    sustainable = [j for j in range(f.rung) if restart[j] <= segment_s * settings.safety_factor]
    target = sustainable[-1] if sustainable else 0
    if restart[target] >= remaining_s:
        return None
    return target, remaining_s, restart[target]


@dataclass
class AbandonRule:
    """Drop an in-flight feature download for a lower rung (see the module docstring); None: go on."""

    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "abandon"

    def choose(self, state: AbrState) -> Decision | None:
        if state.in_flight is None:
            return None
        return self.judge(state.in_flight, state.sizes(), state.buffer_s, state.segment_s)

    def judge(self, f: InFlight, sizes: list[float], buffer_s: float, segment_s: float) -> Decision | None:
        """The decision for one flight (what `choose` does, without building a state per chunk)."""
        verdict = abandon_target(f, sizes, buffer_s, segment_s, self.settings)
        if verdict is None:
            return None
        target, remaining_s, restart_s = verdict
        rate = f.received * 8 / (f.elapsed_s - f.ttfb_s)
        return Decision(target, self.name, f"{remaining_s:.2f} s left at {rate / 1e3:.0f} kbit/s > buffer "
                        f"{buffer_s:.2f} s and one GOP; rung {target} takes {restart_s:.2f} s")
