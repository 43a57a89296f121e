// An SPZ file as Niantic's reference loader (nianticlabs/spz, compiled to WASM by @spz-loader/core) decodes it,
// in OpenCV's axes (RDF), as JSON on stdout: node spz-reference.mjs FILE.spz
// The package activates what the loader returns: scales exp'd, alphas through the sigmoid, colours
// 0.5 + Y_0 * DC; rotations xyzw; sh as stored (coefficient-major, channel inner).
import { readFileSync } from "node:fs";

// The package's bundle replaces node:module with a stub; taken for a browser renderer, it instantiates its
// embedded WASM directly.
process.type = "renderer";
const { loadSpz } = await import("@spz-loader/core");

const cloud = await loadSpz(new Uint8Array(readFileSync(process.argv[2])), {
  colorScaleFactor: 0.28209479177387814,
  unpackOptions: { coordinateSystem: "RDF" },
});
const out = { numPoints: cloud.numPoints, shDegree: cloud.shDegree };
for (const key of ["positions", "scales", "rotations", "alphas", "colors", "sh"]) out[key] = Array.from(cloud[key]);
process.stdout.write(JSON.stringify(out));
