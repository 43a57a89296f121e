// Decode JPEG XL files the way the web player does (jxl-oxide-wasm -> 16-bit PNG -> fast-png) and write each
// image's samples for the Python tests to compare with OpenImageIO's decode.
//
//   node tools/jxl-decode.mjs OUT_DIR FILE.jxl...
//
// For each FILE.jxl: OUT_DIR/<index>.raw (samples row-major, interleaved, little-endian uint16 or uint8) and one
// line of JSON on stdout: {"file", "width", "height", "channels", "depth", "raw"}. Exit 1 with one line on
// stderr when a file does not decode.
import { readFileSync, writeFileSync } from "node:fs";
import { join } from "node:path";
import { decode } from "fast-png";
import { JxlImage, initSync } from "jxl-oxide-wasm";

initSync({ module: readFileSync(new URL(import.meta.resolve("jxl-oxide-wasm/module.wasm"))) });

const [outDir, ...files] = process.argv.slice(2);
if (!outDir || files.length === 0) {
  process.stderr.write("usage: node tools/jxl-decode.mjs OUT_DIR FILE.jxl...\n");
  process.exit(2);
}

files.forEach((file, index) => {
  const image = new JxlImage();
  try {
    image.feedBytes(readFileSync(file));
    // tryInit succeeds once the header is in; `loaded` only when every pass of the frame is. A truncated file
    // would otherwise render as a partial (progressive) image.
    if (!image.tryInit() || !image.loaded) throw new Error("incomplete JPEG XL stream");
    const png = decode(image.render().encodeToPng());
    const raw = join(outDir, `${index}.raw`);
    const samples = png.data;
    writeFileSync(raw, new Uint8Array(samples.buffer, samples.byteOffset, samples.byteLength));
    const info = { file, width: png.width, height: png.height, channels: png.channels, depth: png.depth, raw };
    process.stdout.write(`${JSON.stringify(info)}\n`);
  } catch (err) {
    process.stderr.write(`jxl-decode: ${file}: ${err instanceof Error ? err.message : err}\n`);
    process.exit(1);
  } finally {
    image.free();
  }
});
