// The feature decoder: one worker per feature stream. The main thread streams each GOP's init and media bytes
// in as they arrive (fetch's ReadableStream); mp4box.js demuxes them into samples as they come, and a WebCodecs
// VideoDecoder turns them into 10-bit frames whose luma plane is copied out as a Uint16Array (never through an
// 8-bit RGB path). Decoding is credit-based: the main thread grants one credit per frame it has room for in its
// ring, so only a bounded number of frames are ever decoded ahead of the renderer.
import { createFile, DataStream, Endianness, MP4BoxBuffer, type ISOFile, type Sample } from "mp4box";

interface Job {
  gop: number;
  rung: number;
  side: number;
  frames: number;
  codec: string;
  file: ISOFile;
  received: number;
  ended: boolean;
  samples: Sample[];
  description: Uint8Array | undefined;
  trackId: number;
  fed: number;
  output: number;
  failed: boolean;
}

const jobs: Job[] = [];
let decoder: VideoDecoder | null = null;
let configured: string | null = null;
let credit = 0;
let pumping = false;
let epoch = 0;

function post(msg: unknown, transfer: Transferable[] = []): void {
  self.postMessage(msg, { transfer });
}

function fail(job: Job, message: string): void {
  if (job.failed) return;
  job.failed = true;
  post({ type: "error", gop: job.gop, rung: job.rung, message });
}

function av1cPayload(file: ISOFile, trackId: number): Uint8Array | undefined {
  const trak = file.getTrackById(trackId);
  // mp4box.js types the sample entry without its av1C child box
  const entry = (trak?.mdia?.minf?.stbl?.stsd?.entries?.[0] ?? null) as {
    av1C?: { write(s: DataStream): void };
  } | null;
  const box = entry?.av1C;
  if (!box) return undefined;
  const stream = new DataStream(undefined, 0, Endianness.BIG_ENDIAN);
  box.write(stream);
  return new Uint8Array(stream.buffer as ArrayBuffer, 8); // the payload, without the box header
}

function open(msg: {
  gop: number;
  rung: number;
  side: number;
  frames: number;
  codec: string;
  init: ArrayBuffer;
}): void {
  const file = createFile();
  const job: Job = {
    gop: msg.gop,
    rung: msg.rung,
    side: msg.side,
    frames: msg.frames,
    codec: msg.codec,
    file,
    received: 0,
    ended: false,
    samples: [],
    description: undefined,
    trackId: -1,
    fed: 0,
    output: 0,
    failed: false,
  };
  file.onError = (_module: string, message: string) => fail(job, `the feature segment does not parse (${message})`);
  file.onReady = (info) => {
    const track = info.videoTracks[0];
    if (!track || info.videoTracks.length !== 1) return fail(job, "the feature segment has no single video track");
    if (track.video && (track.video.width !== 4 * job.side || track.video.height !== 4 * job.side)) {
      return fail(
        job,
        `the feature track is ${track.video.width}x${track.video.height}, not ${4 * job.side}x${4 * job.side}`,
      );
    }
    job.trackId = track.id;
    job.description = av1cPayload(file, track.id);
    file.setExtractionOptions(track.id, null, { nbSamples: 1 << 20 });
    file.start();
  };
  file.onSamples = (_id, _user, samples) => {
    for (const s of samples) {
      if (job.samples.length >= job.frames) return fail(job, `the feature segment has more than ${job.frames} frames`);
      job.samples.push(s);
    }
    pump();
  };
  const init = MP4BoxBuffer.fromArrayBuffer(msg.init, 0);
  file.appendBuffer(init);
  job.received = msg.init.byteLength;
  jobs.push(job);
}

function feed(gop: number, data: ArrayBuffer, last: boolean): void {
  const job = jobs.find((j) => j.gop === gop && !j.ended);
  if (!job) return;
  if (data.byteLength) {
    const buf = MP4BoxBuffer.fromArrayBuffer(data, job.received);
    job.received += data.byteLength;
    try {
      job.file.appendBuffer(buf, last);
    } catch (e) {
      fail(job, `the feature segment does not parse (${e instanceof Error ? e.message : e})`);
    }
  }
  if (last) {
    job.ended = true;
    job.file.flush();
    if (!job.failed && job.samples.length !== job.frames) {
      fail(job, `the feature segment of GOP ${gop} holds ${job.samples.length} frames, expected ${job.frames}`);
    }
    pump();
  }
}

function onFrame(frame: VideoFrame, mine: number): void {
  const job = jobs[0];
  if (mine !== epoch || !job) {
    frame.close();
    return;
  }
  const side = 4 * job.side;
  try {
    if ((frame.format as string | null) !== "I420P10" || frame.codedWidth !== side || frame.codedHeight !== side) {
      throw new Error(
        `a decoded feature frame is ${frame.format} ${frame.codedWidth}x${frame.codedHeight}, expected I420P10 ${side}x${side}`,
      );
    }
    const all = new Uint8Array(frame.allocationSize());
    const start = performance.now();
    void frame.copyTo(all).then((layout) => {
      const luma = layout[0]!;
      const plane = new Uint16Array(side * side);
      for (let row = 0; row < side; row++) {
        plane.set(new Uint16Array(all.buffer, luma.offset + row * luma.stride, side), row * side);
      }
      frame.close();
      if (mine !== epoch) return;
      const index = job.output++;
      post({ type: "frame", gop: job.gop, rung: job.rung, index, data: plane, copyMs: performance.now() - start }, [
        plane.buffer,
      ]);
      if (job.output === job.frames) jobs.shift();
      pump();
    });
  } catch (e) {
    frame.close();
    fail(job, e instanceof Error ? e.message : String(e));
  }
}

function makeDecoder(): VideoDecoder {
  const mine = epoch;
  return new VideoDecoder({
    output: (f) => onFrame(f, mine),
    error: (e) => {
      if (jobs[0]) fail(jobs[0], `the AV1 decoder failed (${e.message})`);
      decoder = null;
      configured = null;
    },
  });
}

async function pump(): Promise<void> {
  if (pumping) return;
  pumping = true;
  try {
    for (;;) {
      const job = jobs[0];
      if (!job || job.failed) break;
      if (job.trackId < 0) break;
      if (credit <= 0 || job.fed >= job.samples.length) break;
      const key = job.codec + (job.description?.join(",") ?? "");
      if (!decoder || decoder.state === "closed") decoder = makeDecoder();
      if (configured !== key) {
        const config: VideoDecoderConfig = {
          codec: job.codec,
          codedWidth: 4 * job.side,
          codedHeight: 4 * job.side,
          optimizeForLatency: true,
        };
        if (job.description) config.description = job.description;
        const { supported } = await VideoDecoder.isConfigSupported(config);
        if (!supported) {
          post({ type: "unsupported", message: `this browser's WebCodecs cannot decode ${job.codec} (AV1 10-bit)` });
          job.failed = true;
          break;
        }
        decoder.configure(config);
        configured = key;
      }
      const s = job.samples[job.fed]!;
      if (job.fed === 0 && !s.is_sync) {
        fail(job, `the feature segment of GOP ${job.gop} does not start with a key frame`);
        break;
      }
      decoder.decode(new EncodedVideoChunk({ type: s.is_sync ? "key" : "delta", timestamp: job.fed, data: s.data! }));
      job.fed++;
      credit--;
      if (job.fed === job.frames) await decoder.flush().catch(() => undefined);
    }
  } finally {
    pumping = false;
  }
}

self.onmessage = (event: MessageEvent) => {
  const msg = event.data;
  switch (msg.type) {
    case "open":
      open(msg);
      break;
    case "chunk":
      feed(msg.gop, msg.data, msg.last);
      break;
    case "credit":
      credit += msg.n;
      void pump();
      break;
    case "reset":
      epoch++;
      jobs.length = 0;
      credit = 0;
      if (decoder && decoder.state !== "closed") decoder.close();
      decoder = null;
      configured = null;
      break;
  }
};
