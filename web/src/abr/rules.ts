// The throughput, BOLA, BOLA-E, insufficient-buffer and DYNAMIC rules (stgs/client/abr/rules.py, ported line for line:
// the same arithmetic in the same order, so the decisions match the Python simulator's vectors).
import {
  type AbrRule,
  type AbrSettings,
  type AbrState,
  type Decision,
  DEFAULT_SETTINGS,
  fixed,
  sizes,
  stateLatencyS,
  sustainedBits,
  throughputKbps,
} from "./state";

/** Python's "{:g}": up to six significant digits, trailing zeros dropped. */
function g(v: number): string {
  return String(Number(v.toPrecision(6)));
}

function g3(v: number): string {
  if (v === 0) return "0";
  const e = Math.floor(Math.log10(Math.abs(v)));
  if (e < -4 || e >= 3) {
    const [m, x] = v.toExponential(2).split("e");
    const mant = String(Number(m));
    const exp = Number(x);
    return `${mant}e${exp < 0 ? "-" : "+"}${String(Math.abs(exp)).padStart(2, "0")}`;
  }
  return String(Number(v.toPrecision(3)));
}
export { g, g3 };

export function highestFitting(state: AbrState, kbps: number, seconds: number, bits?: number[]): number {
  const budget = kbps * 1e3 * (seconds - stateLatencyS(state));
  let best = 0;
  (bits ?? sizes(state).map((b) => state.keyframeBits + b)).forEach((b, i) => {
    if (b <= budget) best = i;
  });
  return best;
}

export class ThroughputRule implements AbrRule {
  readonly name = "throughput";
  constructor(readonly settings: AbrSettings = DEFAULT_SETTINGS) {}

  choose(state: AbrState): Decision {
    const st = this.settings;
    const kbps = throughputKbps(state.samples, st);
    if (kbps === null) return { index: 0, rule: this.name, reason: "no throughput sample yet: lowest rung" };
    const T = state.segmentS;
    const latency = stateLatencyS(state);
    const spend = kbps * st.safetyFactor;
    const sustained = sustainedBits(state, st.sustainedGops);
    let best = highestFitting(state, spend, T, sustained);
    let held = "";
    const heldAt = state.current ?? 0; // from the lowest rung at start-up
    if (best > heldAt) {
      const up = highestFitting(state, spend * (1 - st.switchUpHeadroom), T, sustained);
      if (up < best) {
        best = Math.max(up, heldAt);
        held = ` (up needs ${g(st.switchUpHeadroom)} of the budget to spare)`;
      }
    }
    const budget = (spend * (T - latency)) / T;
    const rtt = latency ? ` after ${fixed(latency * 1e3, 0)} ms of round trips` : "";
    return {
      index: best,
      rule: this.name,
      reason:
        `estimate ${fixed(kbps, 0)} kbit/s x ${g(st.safetyFactor)} = budget ` +
        `${fixed(budget, 0)} kbit/s${rtt}; rung ${best} sustains ${fixed(sustained[best]! / T / 1e3, 0)}${held}`,
    };
  }
}

export class BolaRule implements AbrRule {
  readonly name = "bola";
  constructor(readonly settings: AbrSettings = DEFAULT_SETTINGS) {}

  parameters(state: AbrState): [number[], number[], number, number] {
    const s = sustainedBits(state, this.settings.sustainedGops);
    const utilities = s.map((x) => Math.log(x / s[0]!) + 1);
    const minBuffer = this.settings.bolaMinBufferS || state.segmentS;
    const target = Math.max(state.bufferCapacityS - state.segmentS, minBuffer + state.segmentS);
    const gp = Math.max(utilities[utilities.length - 1]! - 1, 1e-9) / (target / minBuffer - 1);
    return [s, utilities, minBuffer / gp, gp];
  }

  bestAt(state: AbrState, bufferS: number): [number, number] {
    const [s, utilities, v, gp] = this.parameters(state);
    const scores = utilities.map((u, i) => (v * (u + gp) - bufferS) / s[i]!);
    let best = 0;
    for (let i = 1; i < scores.length; i++) if (scores[i]! >= scores[best]!) best = i;
    return [best, scores[best]!];
  }

  thresholds(state: AbrState, rung: number): [number, number] {
    const [s, utilities, v, gp] = this.parameters(state);
    const crossing = (lo: number, hi: number) =>
      (v * ((utilities[lo]! + gp) * s[hi]! - (utilities[hi]! + gp) * s[lo]!)) / (s[hi]! - s[lo]!);
    let low = -Infinity;
    for (let i = 0; i < rung; i++) if (s[i]! < s[rung]!) low = Math.max(low, crossing(i, rung));
    if (low === -Infinity) low = 0;
    let high = Infinity;
    for (let i = rung + 1; i < s.length; i++) if (s[i]! > s[rung]!) high = Math.min(high, crossing(rung, i));
    return [Math.max(low, 0), high];
  }

  choose(state: AbrState): Decision {
    const [, , v, gp] = this.parameters(state);
    const [best, score] = this.bestAt(state, state.bufferS);
    return {
      index: best,
      rule: this.name,
      reason:
        `buffer ${fixed(state.bufferS, 2)} s, V ${g3(v)}, gamma*p ${g3(gp)}: ` + `best score ${g3(score)} per bit`,
    };
  }
}

export class BolaERule implements AbrRule {
  readonly name = "bola-e";
  placeholderS = 0;
  steady = false;
  last: number | null = null;
  readonly bola: BolaRule;
  readonly throughput: ThroughputRule;

  constructor(readonly settings: AbrSettings = DEFAULT_SETTINGS) {
    this.bola = new BolaRule(settings);
    this.throughput = new ThroughputRule(settings);
  }

  choose(state: AbrState): Decision {
    const T = state.segmentS;
    const tp = this.throughput.choose(state).index;
    if (this.steady && state.playing && state.bufferS <= 1e-9) {
      this.steady = false;
      this.placeholderS = 0;
    }
    let rung: number;
    let reason: string;
    if (!this.steady) {
      rung = tp;
      this.placeholderS = Math.max(0, this.bola.thresholds(state, rung)[0] - state.bufferS);
      this.steady = state.bufferS >= T;
      reason = `start-up: throughput's rung ${rung}; placeholder ${fixed(this.placeholderS, 2)} s so BOLA agrees`;
    } else {
      this.placeholderS += state.waitedS;
      const virtual = state.bufferS + this.placeholderS;
      rung = this.bola.bestAt(state, virtual)[0];
      reason = `buffer ${fixed(state.bufferS, 2)} + placeholder ${fixed(this.placeholderS, 2)} s: BOLA's rung ${rung}`;
      if (this.last !== null && rung > this.last && rung > tp) {
        rung = Math.max(tp, this.last);
        reason += `, held at ${rung} (BOLA-O: above what the throughput sustains)`;
      }
      const excess = virtual - this.bola.thresholds(state, rung)[1];
      if (excess > 0) this.placeholderS = Math.max(0, this.placeholderS - excess);
    }
    this.last = rung;
    return { index: rung, rule: this.name, reason };
  }
}

export class InsufficientBufferRule {
  readonly name = "insufficient-buffer";
  constructor(readonly settings: AbrSettings = DEFAULT_SETTINGS) {}

  choose(state: AbrState): Decision | null {
    const kbps = throughputKbps(state.samples, this.settings);
    if (kbps === null || !state.playing) return null;
    const window = state.bufferS * this.settings.insufficientBufferSafety;
    const cap = highestFitting(state, kbps, window, sustainedBits(state, this.settings.sustainedGops));
    return {
      index: cap,
      rule: this.name,
      reason:
        `buffer ${fixed(state.bufferS, 2)} s: rung ${cap} is the highest that arrives in ` +
        `${fixed(window, 2)} s at ${fixed(kbps, 0)} kbit/s`,
    };
  }
}

export class DynamicRule implements AbrRule {
  readonly name = "dynamic";
  usingBola = false;
  readonly throughput: ThroughputRule;
  readonly bola: BolaERule;
  readonly insufficient: InsufficientBufferRule;

  constructor(readonly settings: AbrSettings = DEFAULT_SETTINGS) {
    this.throughput = new ThroughputRule(settings);
    this.bola = new BolaERule(settings);
    this.insufficient = new InsufficientBufferRule(settings);
  }

  choose(state: AbrState): Decision {
    const s = this.settings;
    if (this.usingBola && state.bufferS < s.dynamicBolaOff * state.bufferCapacityS) this.usingBola = false;
    else if (!this.usingBola && state.bufferS >= s.dynamicBolaOn * state.bufferCapacityS) this.usingBola = true;
    const throughput = this.throughput.choose(state);
    const bola = this.bola.choose(state);
    const band = this.usingBola ? `>= ${g(s.dynamicBolaOff)}` : `< ${g(s.dynamicBolaOn)}`;
    const where = `dynamic: buffer ${fixed(state.bufferS, 2)} s ${band} x capacity ${fixed(state.bufferCapacityS, 2)} s`;
    let chosen: Decision;
    if (!this.usingBola)
      chosen = { index: throughput.index, rule: throughput.rule, reason: `${where}; ${throughput.reason}` };
    else if (bola.index < throughput.index) {
      chosen = {
        index: throughput.index,
        rule: throughput.rule,
        reason: `${where}, but bola's rung ${bola.index} is below ` + `throughput's; ${throughput.reason}`,
      };
    } else chosen = { index: bola.index, rule: bola.rule, reason: `${where}; ${bola.reason}` };
    const cap = this.insufficient.choose(state);
    if (cap !== null && cap.index < chosen.index)
      return { index: cap.index, rule: cap.rule, reason: `${chosen.reason}; capped: ${cap.reason}` };
    return chosen;
  }
}

export class FixedRule implements AbrRule {
  readonly name = "fixed";
  constructor(readonly index: number) {}

  choose(): Decision {
    return { index: this.index, rule: this.name, reason: `pinned rung ${this.index}` };
  }
}
