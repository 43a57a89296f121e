// Replay decision vectors (stgs.harness.vectors) through the page's ABR rules (dist/node/abr.mjs, built by
// build.mjs) and print one line of JSON per playback: {"rule", "scenario", "steps", "mismatches": [{"step",
// "python", "web"}]}. The Python rules are the reference; the page's must give the same rung from the same rule.
//
//   node tools/abr-replay.mjs VECTORS.json
import { readFileSync } from "node:fs";
import { DEFAULT_SETTINGS, makeRule } from "../dist/node/abr.mjs";

const [input] = process.argv.slice(2);
if (!input) {
  process.stderr.write("usage: node tools/abr-replay.mjs VECTORS.json\n");
  process.exit(2);
}
const { vectors } = JSON.parse(readFileSync(input, "utf8"));
for (const v of vectors) {
  const settings = { ...DEFAULT_SETTINGS };
  for (const key of Object.keys(DEFAULT_SETTINGS)) if (key in v.settings) settings[key] = v.settings[key];
  const rule = makeRule(v.rule, settings);
  const mismatches = [];
  v.steps.forEach((step, i) => {
    const got = rule.choose(step.state);
    const want = step.decision;
    if (got.index !== want.index || got.rule !== want.rule) {
      mismatches.push({ step: i, python: want, web: got });
    }
  });
  process.stdout.write(
    `${JSON.stringify({ rule: v.rule, scenario: v.scenario, steps: v.steps.length, mismatches })}\n`,
  );
}
