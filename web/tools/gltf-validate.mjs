// The Khronos glTF validator's report of a .glb, as JSON on stdout: node gltf-validate.mjs FILE.glb
import { readFileSync } from "node:fs";
import validator from "gltf-validator";

const report = await validator.validateBytes(new Uint8Array(readFileSync(process.argv[2])));
process.stdout.write(JSON.stringify(report));
