// Build the web player into dist/: every script and the JPEG XL decoder's WASM under content-hashed names (served
// immutable), index.html naming them (served with a short cache life), and dist/node/abr.mjs, the ABR rules
// for the conformance replay under Node. `node build.mjs` (npm run build); the type check is `npm run check`.
// `node build.mjs --bench` builds dist-bench/ instead: the same page whose entry is bench/spark.ts (Spark against
// our splat pass; bench/web/web_spark.py), never shipped. Spark makes its sort worker from a blob: URL, which the
// player's CSP (worker-src 'self') refuses; the bench build writes that worker out as a same-origin asset.
import { createHash } from "node:crypto";
import { mkdirSync, readFileSync, rmSync, writeFileSync, renameSync } from "node:fs";
import { basename, join } from "node:path";
import * as esbuild from "esbuild";

const here = new URL(".", import.meta.url).pathname;
const bench = process.argv.includes("--bench");
const tmp = join(here, bench ? "dist-bench.tmp" : "dist.tmp");
const out = join(here, bench ? "dist-bench" : "dist");
rmSync(tmp, { recursive: true, force: true });
mkdirSync(join(tmp, "assets"), { recursive: true });

const hashed = (name, bytes) => {
  const digest = createHash("sha256").update(bytes).digest("hex").slice(0, 12);
  const dot = name.lastIndexOf(".");
  return `${name.slice(0, dot)}-${digest}${name.slice(dot)}`;
};

// Spark's worker source is a string literal in its module; the bench build serves it as a file instead.
let sparkWorker = null;
const sparkPatch = {
  name: "spark-worker-file",
  setup(b) {
    b.onLoad({ filter: /@sparkjsdev[\\/]spark[\\/]dist[\\/]spark\.module\.js$/ }, (args) => {
      const source = readFileSync(args.path, "utf8");
      const literal = /^const jsContent = ('(?:[^'\\]|\\.)*');$/m.exec(source);
      const blobUrl = "(self.URL || self.webkitURL).createObjectURL(blob)";
      if (!literal || !source.includes(blobUrl))
        throw new Error("Spark's worker is not where the bench build expects it");
      sparkWorker = new Function(`return ${literal[1]}`)();
      return { contents: source.replace(blobUrl, "self.sparkWorkerUrl"), loader: "js" };
    });
  },
};

const result = await esbuild.build({
  entryPoints: {
    main: bench ? "bench/spark.ts" : "src/main.ts",
    "keyframe.worker": "src/workers/keyframe.worker.ts",
    "feature.worker": "src/workers/feature.worker.ts",
    "sort.worker": "src/workers/sort.worker.ts",
  },
  bundle: true,
  format: "esm",
  target: "es2022",
  minify: true,
  sourcemap: false,
  legalComments: "none",
  entryNames: "[name]-[hash]",
  outdir: join(tmp, "assets"),
  metafile: true,
  logLevel: "warning",
  plugins: bench ? [sparkPatch] : [],
});
const assets = {};
for (const [file, meta] of Object.entries(result.metafile.outputs)) {
  if (!meta.entryPoint) continue;
  const name = basename(file).replace(/-[A-Z0-9]+\.js$/, "");
  assets[name] = `assets/${basename(file)}`;
}

const wasm = readFileSync(join(here, "node_modules/jxl-oxide-wasm/jxl_oxide_wasm_bg.wasm"));
assets.jxl = `assets/${hashed("jxl.wasm", wasm)}`;
writeFileSync(join(tmp, assets.jxl), wasm);
if (bench) {
  assets.sparkWorker = `assets/${hashed("spark-worker.js", sparkWorker)}`;
  writeFileSync(join(tmp, assets.sparkWorker), sparkWorker);
}
const css = readFileSync(join(here, "src/player.css"));
assets.css = `assets/${hashed("player.css", css)}`;
writeFileSync(join(tmp, assets.css), css);

const html = readFileSync(join(here, "src/index.html"), "utf8")
  .replace("%CSS%", assets.css)
  .replace("%MAIN%", assets.main)
  .replace("%ASSETS%", JSON.stringify(assets).replaceAll("'", "&#39;"));
writeFileSync(join(tmp, "index.html"), html);
writeFileSync(join(tmp, "assets.json"), `${JSON.stringify(assets, null, 1)}\n`);

if (!bench)
  await esbuild.build({
    entryPoints: ["src/abr/index.ts"],
    bundle: true,
    format: "esm",
    platform: "node",
    target: "node20",
    outfile: join(tmp, "node", "abr.mjs"),
    logLevel: "warning",
  });

rmSync(out, { recursive: true, force: true });
renameSync(tmp, out);
process.stdout.write(`web player built: ${Object.keys(assets).length} assets in ${bench ? "dist-bench" : "dist"}/\n`);
