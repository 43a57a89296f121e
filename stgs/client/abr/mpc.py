"""The look-ahead rule: model-predictive control over the next GOPs with their exact sizes and rendered quality.

RobustMPC (Yin et al., SIGCOMM 2015) with what only a packaged STGS scene
can tell: stats.json gives every upcoming GOP's keyframe and per-rung
feature bytes and per-rung rendered PSNR, so the plan is made on the real
segments, not on @bandwidth. Each decision enumerates every rung sequence
over the horizon (vectorised; 7 rungs x 5 GOPs is 16,807 plans), runs the
buffer forward with the round trips and a robust throughput (one of
stgs/client/abr/predict.py's lower bounds, `mpc_predictor`), scores

    Σ_j q_j − μ · (stall + start-up + ρ · shortfall) − w · Σ_j |q_j − q_{j−1}|

with q = the GOP's quality (`mpc_utility = "psnr"`, the default: dB as
stats.json gives it, stgs.tree.rung_quality; bit rate where the scene gives
none) or its whole-GOP bit rate (`"bitrate"`: Mbit/s, Pensieve's linear
QoE), where the shortfall is how far the plan ends below a reservoir of half
the buffer capacity (ρ = 0.2): a five-GOP horizon is shorter than a 25-s
buffer, and without it a plan spends the buffer down and stalls at the next
fade. With `mpc_buffer_constraint` the plans that end below the reservoir
are out as well, as long as one is left. It takes the first rung of the best
plan, unless holding the current rung over the horizon scores within the
hold margin of it.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from functools import cache

import numpy as np

from stgs.client.abr.predict import MIN_KBPS, harmonic_kbps, predict_kbps, relative_error
from stgs.client.abr.state import AbrSettings, AbrState, Decision, UpcomingGOP, latency_s


@cache
def _plans(rungs: int, horizon: int) -> np.ndarray:
    return np.array(list(itertools.product(range(rungs), repeat=horizon)), dtype=np.int64).reshape(-1, horizon)


@dataclass
class MpcRule:
    settings: AbrSettings = field(default_factory=AbrSettings)
    name: str = "mpc"
    errors: list[float] = field(default_factory=list)
    """Relative errors of past throughput predictions."""
    predicted: tuple[int, float] | None = field(default=None, repr=False)
    """(samples seen, kbit/s) of the last prediction, to measure its error when the next sample arrives."""

    def predict_kbps(self, state: AbrState) -> tuple[float, float] | None:
        """(harmonic-mean kbit/s, the kbit/s plans run at: `mpc_predictor`'s), or None without samples."""
        samples = list(state.samples)
        if not samples:
            return None
        kbps = [s.kbps for s in samples]
        if self.predicted is not None and self.predicted[0] < len(samples):
            self.errors.append(relative_error(self.predicted[1], kbps[-1]))
        harmonic = harmonic_kbps(kbps[-self.settings.mpc_history:])
        self.predicted = (len(samples), harmonic)
        return harmonic, predict_kbps(self.settings.mpc_predictor, kbps, self.errors, self.settings)

    def table(self, state: AbrState) -> list[UpcomingGOP]:
        """The GOPs to plan over, the next one first (the scene's sizes where known, else repeats of the next)."""
        gops = list(state.upcoming)[: self.settings.mpc_horizon]
        if not gops:
            gops = [UpcomingGOP(state.keyframe_bits, state.sizes())] * self.settings.mpc_horizon
        gops[0] = UpcomingGOP(state.keyframe_bits, state.sizes(), gops[0].psnr)
        return gops

    def choose(self, state: AbrState) -> Decision:
        predicted = self.predict_kbps(state)
        if predicted is None:
            return Decision(0, self.name, "no throughput sample yet: lowest rung")
        harmonic, robust = predicted
        gops = self.table(state)
        T, rungs = state.segment_s, len(state.bandwidths)
        s = self.settings
        psnr = s.mpc_utility == "psnr" and all(g.psnr is not None and None not in g.psnr for g in gops)
        bits = np.array([[g.keyframe_bits + b for b in g.segment_bits] for g in gops])  # (H, rungs)
        utility = np.array([list(g.psnr or ()) for g in gops]) if psnr else bits / T / 1e6
        mu = s.mpc_rebuffer_psnr if psnr else s.mpc_rebuffer_bitrate
        plans = _plans(rungs, len(gops))
        steps = np.arange(len(gops))
        download = bits.copy()
        trips = np.full(len(gops), float(state.round_trips))
        if state.keyframe_fetched:
            download[0] -= gops[0].keyframe_bits
            trips[0] -= 1
        seconds = trips * latency_s(state.samples) + download[steps, plans] / (max(robust, MIN_KBPS) * 1e3)
        q = utility[steps, plans]
        buffer = np.full(len(plans), state.buffer_s)
        stall = np.zeros(len(plans))
        for j in range(len(gops)):
            if j == 0 and not state.playing:
                stall += seconds[:, 0]
                buffer[:] = T
                continue
            stall += np.maximum(seconds[:, j] - buffer, 0.0)
            buffer = np.minimum(np.maximum(buffer - seconds[:, j], 0.0) + T, state.buffer_capacity_s)
        previous = utility[0, state.current] if state.current is not None else q[:, 0]
        switches = np.abs(q[:, 0] - previous) + np.abs(np.diff(q, axis=1)).sum(axis=1)
        shortfall = np.maximum(s.mpc_reservoir * state.buffer_capacity_s - buffer, 0.0)
        score = q.sum(axis=1) - mu * (stall + s.mpc_reservoir_weight * shortfall) - s.mpc_switch_weight * switches
        if s.mpc_buffer_constraint:
            # plans that end below the reservoir, or below where the buffer stands when it is under it, are out
            feasible = buffer >= min(s.mpc_reservoir * state.buffer_capacity_s, state.buffer_s) - 1e-9
            if feasible.any():
                score = np.where(feasible, score, -np.inf)
        best = int(np.argmax(score))
        held = ""
        if state.current is not None and plans[best, 0] != state.current:
            stay = int(np.argmax((plans == state.current).all(axis=1)))  # holding the rung over the whole horizon
            gain, margin = score[best] - score[stay], s.mpc_switch_margin_s * mu
            if gain < margin:
                held = f"; held at {state.current}: the best plan gains {gain:.2f} < {margin:.2f}"
                best = stay
        rung = int(plans[best, 0])
        unit = "dB" if psnr else "Mbit/s"
        return Decision(rung, self.name, f"throughput {harmonic:.0f} kbit/s, robust {robust:.0f}; plan "
                        f"{'-'.join(str(int(r)) for r in plans[best])} over {len(gops)} GOPs scores "
                        f"{score[best]:.2f} ({unit} utility, stall {stall[best]:.2f} s){held}")
