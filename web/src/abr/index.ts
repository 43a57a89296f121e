// The ABR rules of the page, by the names `stgs play --abr` takes.
import { MpcRule } from "./mpc";
import { BolaERule, BolaRule, DynamicRule, FixedRule, ThroughputRule } from "./rules";
import { type AbrRule, type AbrSettings, DEFAULT_SETTINGS } from "./state";

export * from "./state";
export { BolaERule, BolaRule, DynamicRule, FixedRule, MpcRule, ThroughputRule };

export const RULES: Record<string, (s: AbrSettings) => AbrRule> = {
  mpc: (s) => new MpcRule(s),
  dynamic: (s) => new DynamicRule(s),
  throughput: (s) => new ThroughputRule(s),
  bola: (s) => new BolaRule(s),
  "bola-e": (s) => new BolaERule(s),
};

export function makeRule(name: string, settings: AbrSettings = DEFAULT_SETTINGS): AbrRule {
  const make = RULES[name];
  if (!make) throw new Error(`unknown ABR rule ${name}; known: ${Object.keys(RULES).join(", ")}`);
  return make(settings);
}
