// Decode an AV1 feature segment the way the web player does (WebCodecs VideoDecoder in a real Chromium, driven
// by playwright-core on the system binary) and print each frame's luma plane digest for the Python tests.
//
//   node tools/webcodecs-decode.mjs CHUNKS.json [CHROMIUM]
//
// CHUNKS.json: {"codec", "width", "height", "description" (base64 av1C payload, may be ""), "chunks": [{"key",
// "timestamp", "data" (base64)}]}. Prints one line of JSON: {"supported", "format", "frames": [sha256 of the
// luma plane as little-endian uint16, row-major, in presentation order]}. Exit 1 with one line on stderr on
// failure.
import { createServer } from "node:http";
import { readFileSync } from "node:fs";
import { chromium } from "playwright-core";

const [input, executablePath = "/usr/bin/chromium"] = process.argv.slice(2);
if (!input) {
  process.stderr.write("usage: node tools/webcodecs-decode.mjs CHUNKS.json [CHROMIUM]\n");
  process.exit(2);
}
const job = JSON.parse(readFileSync(input, "utf8"));

// WebCodecs needs a secure context: an empty page on loopback is one.
const server = createServer((_, res) => res.end("<!doctype html><title>webcodecs</title>"));
await new Promise((resolve) => server.listen(0, "127.0.0.1", resolve));
const browser = await chromium.launch({
  executablePath,
  args: [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
  ],
});
try {
  const page = await browser.newPage();
  await page.goto(`http://127.0.0.1:${server.address().port}/`);
  const result = await page.evaluate(async (job) => {
    const bytes = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
    const config = { codec: job.codec, codedWidth: job.width, codedHeight: job.height };
    if (job.description) config.description = bytes(job.description);
    const { supported } = await VideoDecoder.isConfigSupported(config);
    const frames = [];
    let failure = null;
    const decoder = new VideoDecoder({
      output: (f) => frames.push(f),
      error: (e) => {
        failure = String(e);
      },
    });
    decoder.configure(config);
    for (const c of job.chunks) {
      decoder.decode(
        new EncodedVideoChunk({ type: c.key ? "key" : "delta", timestamp: c.timestamp, data: bytes(c.data) }),
      );
    }
    await decoder.flush();
    if (failure) throw new Error(failure);
    frames.sort((a, b) => a.timestamp - b.timestamp);
    const digests = [];
    const format = frames.length ? frames[0].format : null;
    for (const frame of frames) {
      const all = new Uint8Array(frame.allocationSize());
      const [luma] = await frame.copyTo(all);
      const plane = new Uint16Array(job.width * job.height);
      for (let row = 0; row < job.height; row++) {
        plane.set(new Uint16Array(all.buffer, luma.offset + row * luma.stride, job.width), row * job.width);
      }
      const digest = new Uint8Array(await crypto.subtle.digest("SHA-256", plane.buffer));
      digests.push(Array.from(digest, (b) => b.toString(16).padStart(2, "0")).join(""));
      frame.close();
    }
    return { supported, format, frames: digests };
  }, job);
  process.stdout.write(`${JSON.stringify(result)}\n`);
} catch (err) {
  process.stderr.write(`webcodecs-decode: ${err instanceof Error ? err.message.split("\n")[0] : err}\n`);
  process.exitCode = 1;
} finally {
  await browser.close();
  server.close();
}
