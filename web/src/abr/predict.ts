// The look-ahead rule's throughput predictors (stgs/client/abr/predict.py, ported): each turns the GOP throughput
// history (kbit/s, oldest first) and the relative errors of past harmonic-mean predictions into the kbit/s a plan is
// run at. Every predictor is finite and non-negative on any history, 0 on an empty one. The quantile is numpy's to
// the bit; ewma-lower's Math.exp and Math.log may differ from Python's libm in the last bit (the decision vectors
// agree: tests/web/test_contracts.py).
import type { AbrSettings } from "./state";

export const MIN_KBPS = 1e-6;
const MAX_KBPS = 1e12;
const MAX_ERROR = 1e6;

function clamp(kbps: number): number {
  if (Number.isNaN(kbps)) return MIN_KBPS;
  return Math.min(Math.max(kbps, MIN_KBPS), MAX_KBPS);
}

export function relativeError(predictedKbps: number, actualKbps: number): number {
  const actual = clamp(actualKbps);
  return Math.min(Math.abs(clamp(predictedKbps) - actual) / actual, MAX_ERROR);
}

export function harmonicKbps(kbps: number[]): number {
  if (!kbps.length) return 0;
  return kbps.length / kbps.reduce((a, k) => a + 1 / clamp(k), 0);
}

/** numpy.quantile's default (linear between order statistics, interpolated from the nearer one as numpy's _lerp). */
function quantile(values: number[], q: number): number {
  const sorted = values.slice().sort((a, b) => a - b);
  const pos = q * (sorted.length - 1);
  const lo = Math.floor(pos);
  const hi = Math.min(lo + 1, sorted.length - 1);
  const t = pos - lo;
  const diff = sorted[hi]! - sorted[lo]!;
  return t >= 0.5 ? sorted[hi]! - diff * (1 - t) : sorted[lo]! + diff * t;
}

function ewmaLower(kbps: number[], halfLife: number, deviations: number): number {
  const alpha = 1 - 0.5 ** (1 / halfLife);
  const logs = kbps.map((k) => Math.log(clamp(k)));
  let mean = logs[0]!;
  let variance = 0;
  for (const x of logs.slice(1)) {
    const diff = x - mean;
    mean += alpha * diff;
    variance = (1 - alpha) * (variance + alpha * diff * diff);
  }
  return Math.exp(mean - deviations * Math.sqrt(variance));
}

const max = (xs: number[]): number => xs.reduce((a, x) => Math.max(a, x), 0);

export function predictKbps(name: string, kbps: number[], errors: number[], s: AbrSettings): number {
  if (!kbps.length) return 0;
  const n = s.mpcHistory;
  const horizon = s.mpcErrorHorizon;
  switch (name) {
    case "harmonic":
      return harmonicKbps(kbps.slice(-n)) / (1 + max(errors.slice(-n)));
    case "error-bound":
      return harmonicKbps(kbps.slice(-n)) / (1 + max(errors.slice(-horizon)));
    case "quantile":
      return quantile(kbps.slice(-horizon).map(clamp), s.mpcQuantile);
    case "ewma-lower":
      return ewmaLower(kbps, s.mpcEwmaHalfLife, s.mpcEwmaDeviations);
    default:
      throw new Error(`mpcPredictor: unknown predictor ${name}`);
  }
}
