// What every ABR rule shares (stgs/client/abr/state.py, ported): the settings tree, throughput samples and
// estimators, the state a rule sees and the Decision it returns (dash.js's SwitchRequest). The Python module
// is the reference; tests/web/test_contracts.py replays its decisions through these ports under Node.

export interface AbrSettings {
  safetyFactor: number;
  fastHalfLifeS: number;
  slowHalfLifeS: number;
  bolaMinBufferS: number | null;
  dynamicBolaOn: number;
  dynamicBolaOff: number;
  sustainedGops: number;
  switchUpHeadroom: number;
  insufficientBufferSafety: number;
  mpcHorizon: number;
  mpcHistory: number;
  mpcPredictor: "harmonic" | "error-bound" | "quantile" | "ewma-lower";
  mpcErrorHorizon: number;
  mpcQuantile: number;
  mpcEwmaHalfLife: number;
  mpcEwmaDeviations: number;
  mpcBufferConstraint: boolean;
  mpcUtility: "psnr" | "bitrate";
  mpcRebufferPsnr: number;
  mpcRebufferBitrate: number;
  mpcSwitchWeight: number;
  mpcSwitchMarginS: number;
  mpcReservoir: number;
  mpcReservoirWeight: number;
}

/** Every default, in one place (the Python AbrSettings' values). */
export const DEFAULT_SETTINGS: AbrSettings = {
  safetyFactor: 0.9,
  fastHalfLifeS: 3.0,
  slowHalfLifeS: 8.0,
  bolaMinBufferS: null,
  dynamicBolaOn: 0.6,
  dynamicBolaOff: 0.3,
  sustainedGops: 4,
  switchUpHeadroom: 0.1,
  insufficientBufferSafety: 0.5,
  mpcHorizon: 5,
  mpcHistory: 5,
  mpcPredictor: "ewma-lower",
  mpcErrorHorizon: 20,
  mpcQuantile: 0.2,
  mpcEwmaHalfLife: 4.0,
  mpcEwmaDeviations: 1.0,
  mpcBufferConstraint: true,
  mpcUtility: "psnr",
  mpcRebufferPsnr: 10.0,
  mpcRebufferBitrate: 4.3,
  mpcSwitchWeight: 1.0,
  mpcSwitchMarginS: 0.05,
  mpcReservoir: 0.5,
  mpcReservoirWeight: 0.2,
};

export interface ThroughputSample {
  bytes: number;
  seconds: number;
  ttfb: number;
}

export function sampleKbps(s: ThroughputSample): number {
  return (s.bytes * 8) / 1e3 / Math.max(s.seconds - s.ttfb, 1e-6);
}

export interface Decision {
  index: number;
  rule: string;
  reason: string;
}

export interface UpcomingGOP {
  keyframeBits: number;
  segmentBits: number[];
  psnr: number[] | null;
}

export interface AbrState {
  bandwidths: number[];
  segmentS: number;
  bufferS: number;
  bufferCapacityS: number;
  samples: ThroughputSample[];
  keyframeBits: number;
  segmentBits: number[] | null;
  current: number | null;
  roundTrips: number;
  keyframeFetched: boolean;
  waitedS: number;
  upcoming: UpcomingGOP[];
  playing: boolean;
}

export function sizes(state: AbrState): number[] {
  return state.segmentBits !== null ? state.segmentBits.slice() : state.bandwidths.map((b) => b * state.segmentS);
}

/** Per rung: keyframe + features, the mean over the next `gops` GOPs (the next one's own sizes first, then
 * `upcoming`'s as far as they go): AbrState.sustained_bits. */
export function sustainedBits(state: AbrState, gops: number): number[] {
  const table: [number, number[]][] = [[state.keyframeBits, sizes(state)]];
  for (const g of state.upcoming.slice(1, gops)) table.push([g.keyframeBits, g.segmentBits]);
  return state.bandwidths.map((_, i) => table.reduce((a, [k, s]) => a + (k + s[i]!), 0) / table.length);
}

const EWMA_NEGLIGIBLE = 1e-3;

export function ewmaKbps(samples: ThroughputSample[], halfLifeS: number): number | null {
  let estimate = 0;
  let decay = 1;
  for (let i = samples.length - 1; i >= 0; i--) {
    const s = samples[i]!;
    let body = s.seconds - s.ttfb;
    // biome-ignore lint/complexity/useMathMinMax: as the Python twin, a NaN body becomes 1e-6, not NaN
    body = body > 1e-6 ? body : 1e-6;
    const alpha = 0.5 ** (body / halfLifeS);
    estimate += (decay * (1 - alpha) * s.bytes * 8e-3) / body;
    decay *= alpha;
    if (decay < EWMA_NEGLIGIBLE) break;
  }
  if (decay === 1) return null;
  return estimate / (1 - decay);
}

export function throughputKbps(samples: ThroughputSample[], settings: AbrSettings): number | null {
  const fast = ewmaKbps(samples, settings.fastHalfLifeS);
  const slow = ewmaKbps(samples, settings.slowHalfLifeS);
  return fast === null ? null : Math.min(fast, slow!);
}

const LATENCY_SAMPLES = 4;

export function latencyS(samples: ThroughputSample[]): number {
  const recent = samples.slice(-LATENCY_SAMPLES);
  return recent.length ? recent.reduce((a, s) => a + s.ttfb, 0) / recent.length : 0;
}

export function stateLatencyS(state: AbrState): number {
  return latencyS(state.samples) * state.roundTrips;
}

export interface AbrRule {
  readonly name: string;
  choose(state: AbrState): Decision;
}

/** Python's "{:.Nf}" for the reasons (the same numbers in the same words). */
export function fixed(v: number, digits: number): string {
  return v.toFixed(digits);
}
