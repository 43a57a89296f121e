// The look-ahead rule (stgs/client/abr/mpc.py, ported): RobustMPC over the next GOPs' exact sizes and rendered PSNR
// from stats.json. Every rung sequence over the horizon is scored in the same order as the Python's
// itertools.product, so ties break the same way.
import { MIN_KBPS, harmonicKbps, predictKbps, relativeError } from "./predict";
import {
  type AbrRule,
  type AbrSettings,
  type AbrState,
  type Decision,
  DEFAULT_SETTINGS,
  type UpcomingGOP,
  fixed,
  latencyS,
  sampleKbps,
  sizes,
} from "./state";

export class MpcRule implements AbrRule {
  readonly name = "mpc";
  readonly errors: number[] = [];
  predicted: [number, number] | null = null;

  constructor(readonly settings: AbrSettings = DEFAULT_SETTINGS) {}

  predictKbps(state: AbrState): [number, number] | null {
    const samples = state.samples;
    if (!samples.length) return null;
    const kbps = samples.map(sampleKbps);
    if (this.predicted !== null && this.predicted[0] < samples.length) {
      this.errors.push(relativeError(this.predicted[1], kbps[kbps.length - 1]!));
    }
    const harmonic = harmonicKbps(kbps.slice(-this.settings.mpcHistory));
    this.predicted = [samples.length, harmonic];
    return [harmonic, predictKbps(this.settings.mpcPredictor, kbps, this.errors, this.settings)];
  }

  table(state: AbrState): UpcomingGOP[] {
    let gops = state.upcoming.slice(0, this.settings.mpcHorizon);
    if (!gops.length)
      gops = Array.from({ length: this.settings.mpcHorizon }, () => ({
        keyframeBits: state.keyframeBits,
        segmentBits: sizes(state),
        psnr: null,
      }));
    gops[0] = { keyframeBits: state.keyframeBits, segmentBits: sizes(state), psnr: gops[0]!.psnr };
    return gops;
  }

  choose(state: AbrState): Decision {
    const predicted = this.predictKbps(state);
    if (predicted === null) return { index: 0, rule: this.name, reason: "no throughput sample yet: lowest rung" };
    const [harmonic, robust] = predicted;
    const gops = this.table(state);
    const T = state.segmentS;
    const rungs = state.bandwidths.length;
    const s = this.settings;
    const H = gops.length;
    const psnr = s.mpcUtility === "psnr" && gops.every((gp) => gp.psnr?.every((p) => p !== null));
    const bits = gops.map((gp) => gp.segmentBits.map((b) => gp.keyframeBits + b));
    const utility = psnr ? gops.map((gp) => gp.psnr!.slice()) : bits.map((row) => row.map((b) => b / T / 1e6));
    const mu = psnr ? s.mpcRebufferPsnr : s.mpcRebufferBitrate;
    const download = bits.map((row) => row.slice());
    const trips = new Array<number>(H).fill(state.roundTrips);
    if (state.keyframeFetched) {
      download[0] = download[0]!.map((b) => b - gops[0]!.keyframeBits);
      trips[0]! -= 1;
    }
    const latency = latencyS(state.samples);
    const plan = new Array<number>(H).fill(0);
    let bestScore = -Infinity;
    let bestPlan: number[] = plan.slice();
    let bestStall = 0;
    let stayScore = -Infinity;
    let stayPlan: number[] = plan.slice();
    let stayStall = 0;
    const reservoir = s.mpcReservoir * state.bufferCapacityS;
    let anyFeasible = false;
    let feasibleScore = -Infinity;
    let feasiblePlan: number[] = plan.slice();
    let feasibleStall = 0;
    let stayFeasible = false;
    const total = rungs ** H;
    for (let p = 0; p < total; p++) {
      let rest = p;
      for (let j = H - 1; j >= 0; j--) {
        plan[j] = rest % rungs;
        rest = Math.floor(rest / rungs);
      }
      let buffer = state.bufferS;
      let stall = 0;
      let qsum = 0;
      for (let j = 0; j < H; j++) {
        const seconds = trips[j]! * latency + download[j]![plan[j]!]! / (Math.max(robust, MIN_KBPS) * 1e3);
        qsum += utility[j]![plan[j]!]!;
        if (j === 0 && !state.playing) {
          stall += seconds;
          buffer = T;
          continue;
        }
        stall += Math.max(seconds - buffer, 0);
        buffer = Math.min(Math.max(buffer - seconds, 0) + T, state.bufferCapacityS);
      }
      const q0 = utility[0]![plan[0]!]!;
      const previous = state.current !== null ? utility[0]![state.current]! : q0;
      let diffs = 0;
      for (let j = 1; j < H; j++) diffs += Math.abs(utility[j]![plan[j]!]! - utility[j - 1]![plan[j - 1]!]!);
      const switches = Math.abs(q0 - previous) + diffs;
      const shortfall = Math.max(s.mpcReservoir * state.bufferCapacityS - buffer, 0);
      const score = qsum - mu * (stall + s.mpcReservoirWeight * shortfall) - s.mpcSwitchWeight * switches;
      if (score > bestScore) {
        bestScore = score;
        bestPlan = plan.slice();
        bestStall = stall;
      }
      // plans that end below the reservoir (or below where the buffer stands, under it) are out, if any is left
      const feasible = !s.mpcBufferConstraint || buffer >= Math.min(reservoir, state.bufferS) - 1e-9;
      if (feasible) {
        anyFeasible = true;
        if (score > feasibleScore) [feasibleScore, feasiblePlan, feasibleStall] = [score, plan.slice(), stall];
      }
      if (plan.every((r) => r === state.current)) {
        // holding the rung over the whole horizon
        stayScore = score;
        stayPlan = plan.slice();
        stayStall = stall;
        stayFeasible = feasible;
      }
    }
    if (s.mpcBufferConstraint && anyFeasible) {
      [bestScore, bestPlan, bestStall] = [feasibleScore, feasiblePlan, feasibleStall];
      if (!stayFeasible) stayScore = -Infinity;
    }
    let held = "";
    const margin = s.mpcSwitchMarginS * mu;
    if (state.current !== null && bestPlan[0] !== state.current && bestScore - stayScore < margin) {
      held = `; held at ${state.current}: the best plan gains ${fixed(bestScore - stayScore, 2)} < ${fixed(margin, 2)}`;
      [bestScore, bestPlan, bestStall] = [stayScore, stayPlan, stayStall];
    }
    const unit = psnr ? "dB" : "Mbit/s";
    return {
      index: bestPlan[0]!,
      rule: this.name,
      reason:
        `throughput ${fixed(harmonic, 0)} kbit/s, robust ${fixed(robust, 0)}; plan ` +
        `${bestPlan.join("-")} over ${H} GOPs scores ${fixed(bestScore, 2)} (${unit} utility, stall ${fixed(bestStall, 2)} s)${held}`,
    };
  }
}
