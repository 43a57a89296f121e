"""What every ABR rule shares: the settings tree, throughput samples and estimators, the state a rule sees and the
Decision it returns (dash.js's SwitchRequest)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from stgs.errors import FieldError
from stgs.tree import KEYFRAME_REP, paired_keyframe_bytes, rung_quality

MPC_PREDICTORS = ("harmonic", "error-bound", "quantile", "ewma-lower")
"""The look-ahead rule's throughput predictors (stgs/client/abr/predict.py)."""


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
    sustained_gops: int = 4
    """The throughput and BOLA rules decide on each rung's sustained size: keyframe + features, the mean over this
    many GOPs (the next one first, as far as the scene says), not the next GOP's alone, whose size alternates in
    scenes of alternating GOPs (docs/BENCHMARKS.md, "ABR rules over trace sets")."""
    switch_up_headroom: float = 0.1
    """The throughput rule moves up only to a rung whose sustained rate leaves this share of its budget to spare
    (down at once, as soon as the rung it holds no longer fits)."""
    insufficient_buffer_safety: float = 0.5
    """The insufficient-buffer rule lets a sustained GOP's download take at most this fraction of the buffer."""
    abandon_min_s: float = 0.2
    """A feature download is never abandoned before its body has arrived for this long."""
    mpc_horizon: int = 5
    """GOPs the look-ahead rule plans over."""
    mpc_history: int = 5
    """GOP samples in the look-ahead rule's harmonic-mean throughput and its error bound."""
    mpc_predictor: str = "ewma-lower"
    """The look-ahead rule's throughput predictor (stgs/client/abr/predict.py): harmonic (RobustMPC's), error-bound,
    quantile or ewma-lower (docs/BENCHMARKS.md, "ABR rules over trace sets", measures each)."""
    mpc_error_horizon: int = 20
    """GOPs of history the error-bound and quantile predictors read."""
    mpc_quantile: float = 0.2
    """The quantile predictor's quantile."""
    mpc_ewma_half_life: float = 4.0
    """Half-life (GOPs) of the ewma-lower predictor's mean and variance of log throughput."""
    mpc_ewma_deviations: float = 1.0
    """Standard deviations of log throughput the ewma-lower predictor stays below the mean."""
    mpc_buffer_constraint: bool = True
    """Plans that end below the reservoir (or, while the buffer is under it, below where it stands) are out, as
    long as any plan is left; the reservoir's charge applies as well."""
    mpc_utility: str = "psnr"
    """What the look-ahead rule maximises per GOP: the rung's quality (dB; stats.json, against the capture where the
    packager knew the model's own error, stgs.tree.rung_quality; bit rate where the scene gives none), or `bitrate`
    (Pensieve's linear QoE, the published one). docs/BENCHMARKS.md ("Packaging: the auto ladder") measures both on
    the fixed and the auto ladder: the quality utility buys the same quality for fewer bytes where the top rungs
    render alike."""
    mpc_rebuffer_psnr: float = 10.0
    """dB a second of stall costs the PSNR utility (about the dB span of a QP 16-40 ladder)."""
    mpc_rebuffer_bitrate: float = 4.3
    """Mbit/s-GOPs a second of stall costs the bit-rate utility (Pensieve's linear QoE)."""
    mpc_switch_weight: float = 1.0
    """Weight of |utility change| between consecutive GOPs."""
    mpc_switch_margin_s: float = 0.05
    """The look-ahead rule leaves the rung it holds only for a plan scoring more than holding it over the whole
    horizon by what this many seconds of stall cost (hysteresis: 0.5 dB with the PSNR utility)."""
    mpc_reservoir: float = 0.5
    """Fraction of the buffer capacity a plan should leave filled at its end (the horizon is shorter than a large
    buffer: without it, the plan spends the buffer down and a fade after the horizon stalls)."""
    mpc_reservoir_weight: float = 0.2
    """Each second a plan ends below the reservoir costs this fraction of a second of stall."""

    def __post_init__(self) -> None:
        if self.mpc_predictor not in MPC_PREDICTORS:
            raise FieldError("mpc_predictor", f"must be one of {', '.join(MPC_PREDICTORS)}, got {self.mpc_predictor!r}")
        if not 0 <= self.mpc_quantile <= 1:
            raise FieldError("mpc_quantile", f"must be in [0, 1], got {self.mpc_quantile}")
        if self.mpc_error_horizon < 1 or self.mpc_history < 1:
            raise FieldError("mpc_error_horizon" if self.mpc_error_horizon < 1 else "mpc_history", "must be >= 1")
        if self.mpc_ewma_half_life <= 0:
            raise FieldError("mpc_ewma_half_life", f"must be > 0, got {self.mpc_ewma_half_life}")


@dataclass(frozen=True)
class ThroughputSample:
    """One GOP's (or request's) transfer: bytes, seconds from request to last byte, and the time to first byte."""

    bytes: int
    seconds: float
    ttfb: float = 0.0

    @property
    def body_s(self) -> float:
        """Seconds the bytes took to arrive, the round trip excluded."""
        return max(self.seconds - self.ttfb, 1e-6)

    @property
    def kbps(self) -> float:
        """Throughput of the body (the round trip is latency, not bandwidth)."""
        return self.bytes * 8 / 1e3 / self.body_s


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
    ttfb_s: float = 0.0
    """Media seconds from the request to its first byte."""


@dataclass(frozen=True)
class UpcomingGOP:
    """What the packaged scene says of a GOP ahead (stats.json): its sizes and per-rung rendered quality."""

    keyframe_bits: float
    segment_bits: Sequence[float]
    """Feature bits per rung."""
    psnr: Sequence[float] | None = None
    """Rendered PSNR per rung (None: unknown)."""

    @classmethod
    def paired(cls, keyframe_bits: Sequence[float], feature_bits: Sequence[float],
               psnr: Sequence[float] | None = None) -> UpcomingGOP:
        """A GOP whose rungs each play with their own keyframes (`keyframe_bits` per rung): the cheapest keyframes
        are its keyframe_bits, what a rung's keyframes cost beyond them counts to its segment_bits (as
        stgs.client.manifest.Presentation.abr_bandwidths does for @bandwidth)."""
        base = min(keyframe_bits)
        return cls(base, [f + kf - base for f, kf in zip(feature_bits, keyframe_bits, strict=True)], psnr)

    @classmethod
    def from_stats(cls, stats: Any, k: int, rep_ids: list[str],
                   keyframe_reps: list[str] | None = None) -> UpcomingGOP | None:
        """GOP k's keyframe and per-rung media bits and rendered PSNR, from stats.json, or None where it does not
        say (PSNR None unless every rung has a finite one); `keyframe_reps`: the keyframe Representation each rung
        plays with (None: the lossless one for all)."""
        try:
            gop = stats["gops"][k]
            if gop["index"] != k:
                return None
            keyframes = [float(paired_keyframe_bytes(gop, kf)) * 8 for kf in keyframe_reps or [KEYFRAME_REP]]
            sizes = [float(gop["representations"][r]["bytes"]) * 8 for r in rep_ids]
        except (KeyError, IndexError, TypeError, ValueError):
            return None
        if not all(math.isfinite(s) and s > 0 for s in [*keyframes, *sizes]):
            return None
        try:
            psnr = rung_quality(gop["representations"], rep_ids)
        except (KeyError, TypeError, ValueError):
            psnr = None
        psnr = psnr if psnr and all(math.isfinite(p) for p in psnr) else None
        return cls.paired(keyframes * len(sizes) if keyframe_reps is None else keyframes, sizes, psnr)


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
    """Throughput history (one sample per GOP: keyframe and features together), oldest first."""
    keyframe_bits: float = 0.0
    """Size of the next GOP's keyframe segment."""
    segment_bits: Sequence[float] | None = None
    """Size of the next GOP's media segment per rung (None: @bandwidth x duration)."""
    current: int | None = None
    """Rung chosen for the previous GOP."""
    in_flight: InFlight | None = None
    """The feature download being judged (AbandonRule only)."""
    round_trips: int = 1
    """Round trips a GOP costs (2 when its keyframe is fetched before the features are asked for)."""
    keyframe_fetched: bool = False
    """The next GOP's keyframe is already here (its bits and one round trip are spent)."""
    waited_s: float = 0.0
    """Seconds the fetcher waited for buffer room since the previous GOP arrived (BOLA-E's placeholder)."""
    upcoming: Sequence[UpcomingGOP] = ()
    """The next GOP and those after it, as far as the scene says (the look-ahead rule, sustained sizes)."""
    playing: bool = True
    """Playback has started (False: the next GOP decides the start-up delay)."""

    def sizes(self) -> list[float]:
        """Feature bits of the next GOP per rung."""
        if self.segment_bits is not None:
            return [float(b) for b in self.segment_bits]
        return [b * self.segment_s for b in self.bandwidths]

    def sustained_bits(self, gops: int) -> list[float]:
        """Per rung: keyframe + features, the mean over the next `gops` GOPs (the next one's own sizes first, then
        `upcoming`'s as far as they go)."""
        table = [(self.keyframe_bits, self.sizes())]
        table += [(g.keyframe_bits, list(g.segment_bits)) for g in list(self.upcoming)[1:gops]]
        return [sum(k + sizes[i] for k, sizes in table) / len(table) for i in range(len(self.bandwidths))]

    def latency_s(self) -> float:
        """Estimated seconds of round trips per GOP."""
        return latency_s(self.samples) * self.round_trips


EWMA_NEGLIGIBLE = 1e-3
"""An EWMA stops reading older samples once they weigh less than this together (the estimate moves < 0.1 %)."""


def ewma_kbps(samples: Sequence[ThroughputSample], half_life_s: float) -> float | None:
    """Duration-weighted EWMA of sample throughputs (kbit/s, round trips excluded), zero-bias corrected; None
    without samples. Read newest first: each sample weighs (1 − α) times the α of every later one, α = 0.5^(body
    seconds / half-life); the correction divides by 1 − Π α."""
    estimate, decay = 0.0, 1.0
    for s in reversed(samples):
        body = s.seconds - s.ttfb
        body = body if body > 1e-6 else 1e-6
        alpha = 0.5 ** (body / half_life_s)
        estimate += decay * (1 - alpha) * s.bytes * 8e-3 / body
        decay *= alpha
        if decay < EWMA_NEGLIGIBLE:
            break
    if decay == 1.0:
        return None
    return estimate / (1 - decay)


def throughput_kbps(samples: Sequence[ThroughputSample], settings: AbrSettings) -> float | None:
    """The estimate the throughput rule uses: the lower of the fast and slow EWMAs."""
    fast = ewma_kbps(samples, settings.fast_half_life_s)
    slow = ewma_kbps(samples, settings.slow_half_life_s)
    return None if fast is None or slow is None else min(fast, slow)


LATENCY_SAMPLES = 4


def latency_s(samples: Sequence[ThroughputSample]) -> float:
    """Mean time to first byte of the last few samples (0 without samples)."""
    recent = list(samples)[-LATENCY_SAMPLES:]
    return sum(s.ttfb for s in recent) / len(recent) if recent else 0.0


class AbrRule(Protocol):
    """What every rule is: a name for the log, and a Decision for each state."""

    name: str

    def choose(self, state: AbrState) -> Decision:
        """The rung for the next GOP."""
