"""Adaptive bitrate rules: small objects behind one interface (`state.AbrRule`), defaults in one settings place
(`state.AbrSettings`), one module per kind of rule as in web/src/abr/: `rules` (the classic ones), `mpc` and
`predict` (the look-ahead rule), `abandon` (the abandonment judge).

A rule gets an `AbrState` (ladder, throughput history, buffer level, the
next GOP's keyframe and per-Representation segment sizes, the GOPs after it
as far as stats.json says) and returns a `Decision`: the ladder rung, the
rule that decided and the reason with the numbers it used (dash.js's
SwitchRequest). The playback log keeps every decision. Each rung plays with
its own keyframes (manifests/PROFILE.md, "Keyframe rungs"): the cheapest
rung's are the state's keyframe bits, which each rule counts before it
spends anything on features, and what a rung's keyframes cost beyond them
counts to its own size and @bandwidth (Presentation.abr_bandwidths).
Throughput is measured on bodies (the round trip is latency, estimated
apart and budgeted per request).

- `ThroughputRule`: EWMA throughput with a fast and a slow half-life (the
  lower of the two, as dash.js does), times a safety factor; the highest
  rung whose sustained keyframe + features (the mean over the next GOPs)
  arrive within one GOP after the round trips, moving up only with headroom
  to spare (hysteresis) and down at once.
- `BolaRule`: BOLA (Spiteri et al., buffer-based Lyapunov optimisation):
  utility v_m = ln(size_m / size_0) + 1 of the whole GOP (keyframe +
  features, the sustained size as above, as dash.js decides on nominal
  rates); choose argmax (V·(v_m + γp) − buffer) / size_m. Its target
  buffer is the highest level a decision is ever made at (capacity − one
  GOP: the fetcher asks only when a whole GOP fits).
- `BolaERule`: BOLA-E as dash.js runs it: start-up picks by throughput and
  sets a placeholder buffer so BOLA would agree; the placeholder grows while
  the fetcher waits for room, shrinks when it would overfill, vanishes at a
  stall; BOLA-O keeps it from climbing above what the throughput sustains.
- `InsufficientBufferRule`: a cap: a GOP of the rung's sustained size must
  download within a fraction of the buffer at the throughput estimate.
- `DynamicRule`: dash.js's default collection: throughput while the buffer
  is low, BOLA-E once it is full enough (with hysteresis) and only while its
  choice is at least the throughput rule's, then the insufficient-buffer cap.
- `MpcRule` (`mpc`): look-ahead over the next GOPs' exact sizes, with the throughput predictors of `predict`.
- `FixedRule`: one pinned Representation (`qp`).
"""

from __future__ import annotations

from collections.abc import Sequence

from stgs.client.abr.abandon import AbandonRule, abandon_target
from stgs.client.abr.mpc import MpcRule
from stgs.client.abr.rules import (
    BolaERule,
    BolaRule,
    DynamicRule,
    FixedRule,
    InsufficientBufferRule,
    ThroughputRule,
)
from stgs.client.abr.state import (
    AbrRule,
    AbrSettings,
    AbrState,
    Decision,
    InFlight,
    ThroughputSample,
    UpcomingGOP,
    ewma_kbps,
    latency_s,
    throughput_kbps,
)
from stgs.errors import FieldError

__all__ = [
    "RULES",
    "AbandonRule",
    "AbrRule",
    "AbrSettings",
    "AbrState",
    "BolaERule",
    "BolaRule",
    "Decision",
    "DynamicRule",
    "FixedRule",
    "InFlight",
    "InsufficientBufferRule",
    "MpcRule",
    "ThroughputRule",
    "ThroughputSample",
    "UpcomingGOP",
    "abandon_target",
    "ewma_kbps",
    "latency_s",
    "make_rule",
    "throughput_kbps",
]


RULES = {"mpc": MpcRule, "dynamic": DynamicRule, "throughput": ThroughputRule, "bola": BolaRule,
         "bola-e": BolaERule}
"""The adaptive rules by name (PlayConfig.abr)."""


def make_rule(name: str, ladder_qps: Sequence[int | None], qp: int | None, settings: AbrSettings) -> AbrRule:
    """The rule `name`, or a FixedRule on the rung of `qp` when one is pinned."""
    if qp is None:
        return RULES[name](settings)
    if qp not in ladder_qps:
        raise FieldError("qp", f"{qp} is not offered: the scene has QPs {', '.join(str(q) for q in ladder_qps)}")
    return FixedRule(list(ladder_qps).index(qp))
