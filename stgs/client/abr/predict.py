"""The look-ahead rule's throughput predictors: each turns the GOP throughput history (kbit/s, oldest first) and the
relative errors of the past harmonic-mean predictions (MpcRule keeps them) into the kbit/s a plan is run at.

- `harmonic` (RobustMPC's): the harmonic mean of the last `mpc_history` samples, divided by 1 + the largest of the
  last `mpc_history` prediction errors.
- `error-bound`: the same harmonic mean, divided by 1 + the largest error over the last `mpc_error_horizon`
  predictions (one fade stays in the bound for that many GOPs, not five).
- `quantile`: the `mpc_quantile` lower quantile of the last `mpc_error_horizon` samples (a long-tailed trace's
  bursts do not lift it).
- `ewma-lower`: exp(m - k s), with m and s² the exponentially weighted mean and variance of log throughput
  (half-life `mpc_ewma_half_life` GOPs, k = `mpc_ewma_deviations`): a lower bound that widens when the rate is
  erratic.

Every predictor is bounded: finite and non-negative on any history, 0 on an empty one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from stgs.client.abr.state import MPC_PREDICTORS, AbrSettings

MIN_KBPS = 1e-6
"""Throughput below this counts as this (a zero sample would make the harmonic mean and the log infinite)."""
MAX_KBPS = 1e12
"""... and above this as this (a petabit sample: past it the float arithmetic below would overflow)."""
MAX_ERROR = 1e6
"""A relative prediction error is counted at most this (a zero-throughput sample makes it infinite)."""


def relative_error(predicted_kbps: float, actual_kbps: float) -> float:
    """|predicted − actual| / actual, bounded."""
    actual, predicted = _clamp(actual_kbps), _clamp(predicted_kbps)
    return min(abs(predicted - actual) / actual, MAX_ERROR)


def harmonic_kbps(kbps: Sequence[float]) -> float:
    """Harmonic mean (0 without samples)."""
    if not kbps:
        return 0.0
    return len(kbps) / sum(1 / _clamp(k) for k in kbps)


def predict_kbps(name: str, kbps: Sequence[float], errors: Sequence[float], settings: AbrSettings) -> float:
    """The throughput predictor `name` over the history `kbps` and the relative `errors` of past harmonic means."""
    if not kbps:
        return 0.0
    n, horizon = settings.mpc_history, settings.mpc_error_horizon
    if name == "harmonic":
        return harmonic_kbps(kbps[-n:]) / (1 + max(errors[-n:], default=0.0))
    if name == "error-bound":
        return harmonic_kbps(kbps[-n:]) / (1 + max(errors[-horizon:], default=0.0))
    if name == "quantile":
        return float(np.quantile([_clamp(k) for k in kbps[-horizon:]], settings.mpc_quantile))
    if name == "ewma-lower":
        return _ewma_lower(kbps, settings.mpc_ewma_half_life, settings.mpc_ewma_deviations)
    raise ValueError(f"mpc_predictor: unknown predictor {name!r}; known: {', '.join(MPC_PREDICTORS)}")


def _clamp(kbps: float) -> float:
    return min(max(kbps, MIN_KBPS), MAX_KBPS) if math.isfinite(kbps) else (MAX_KBPS if kbps > 0 else MIN_KBPS)


def _ewma_lower(kbps: Sequence[float], half_life: float, deviations: float) -> float:
    alpha = 1 - 0.5 ** (1 / half_life)
    logs = [math.log(_clamp(k)) for k in kbps]
    mean, var = logs[0], 0.0
    for x in logs[1:]:
        diff = x - mean
        mean += alpha * diff
        var = (1 - alpha) * (var + alpha * diff * diff)
    return math.exp(mean - deviations * math.sqrt(var))
