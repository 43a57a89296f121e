// A keyframe decoder: one of a pool of workers that parse a keyframe or static-layer segment (container.ts),
// decode its lossless JPEG XL images with jxl-oxide (WASM; 16-bit output, which the browsers' own JXL decoders
// do not give) and dequantise them, so the main thread gets float attributes ready for the GPU.
import { decode as decodePng } from "fast-png";
import initJxl, { JxlImage } from "jxl-oxide-wasm";
import {
  type Attributes,
  asAttributes,
  LOSSLESS,
  SH1_SPECS,
  dequantize,
  dequantizeWeight,
  quantSpecs,
  readContainer,
  type KeyframeQuant,
} from "../container";
import { SegmentError } from "../errors";

export interface DecodeJob {
  id: number;
  data: ArrayBuffer;
  what: "keyframe" | "static-layer";
  metadata: Record<string, string>;
  want: [string, number[] | null][];
  side: number;
  shDegree: number;
  maxBytes: number;
  /** A keyframe's quantisation (absent: LOSSLESS, and for the static layer). */
  quant?: KeyframeQuant;
  /** Quantised deformation weights: name -> [out, in] of each weight image (empty for float32 weights). */
  fieldShapes?: [string, [number, number]][];
}

export interface DecodedSegment {
  attributes: Attributes;
  /** Float tensors of the container (ranges and deformation weights) by name. */
  floats: Record<string, Float32Array>;
  ms: number;
}

let ready: Promise<unknown> | null = null;

interface ImageShape {
  name: string;
  width: number;
  height: number;
  channels: number;
  levels: number;
}

function decodeImage(bytes: Uint8Array, want: ImageShape, what: string): Uint8Array | Uint16Array {
  const { name, width, height, channels } = want;
  const image = new JxlImage();
  try {
    image.feedBytes(bytes);
    // tryInit succeeds once the header is in; `loaded` only when every pass is (else a progressive partial image)
    if (!image.tryInit() || !image.loaded) throw new SegmentError(`${what} image ${name}: incomplete JPEG XL stream`);
    if (image.width !== width || image.height !== height) {
      throw new SegmentError(`${what} image ${name} is ${image.width}x${image.height}, expected ${width}x${height}`);
    }
    const png = decodePng(image.render().encodeToPng());
    const depth = want.levels <= 256 ? 8 : 16;
    if (png.width !== width || png.height !== height || png.channels !== channels || png.depth !== depth) {
      throw new SegmentError(
        `${what} image ${name} is ${png.width}x${png.height}x${png.channels} at ${png.depth} bits, ` +
          `expected ${width}x${height}x${channels} at ${depth}`,
      );
    }
    return png.data as Uint8Array | Uint16Array;
  } finally {
    image.free();
  }
}

function run(job: DecodeJob): DecodedSegment {
  const start = performance.now();
  const tensors = readContainer(job.data, job.metadata, new Map(job.want), job.maxBytes, job.what);
  const quant = job.quant ?? LOSSLESS;
  const base = quantSpecs(quant);
  const specs = job.shDegree ? [...base, ...SH1_SPECS] : base;
  const decoded: Record<string, Float32Array> = {};
  for (const spec of specs) {
    const codes = decodeImage(
      tensors.get(`image.${spec.name}`) as Uint8Array,
      { ...spec, width: job.side, height: job.side },
      job.what,
    );
    decoded[spec.name] = dequantize(spec, codes, tensors.get(`range.${spec.name}`) as Float32Array);
  }
  const attributes = asAttributes(decoded, job.what);
  const floats: Record<string, Float32Array> = {};
  for (const [name, t] of tensors) if (t instanceof Float32Array && !name.startsWith("range.field.")) floats[name] = t;
  for (const [name, [out, inp]] of job.fieldShapes ?? []) {
    // quantised weights: decoded to the float32 names
    const codes = decodeImage(
      tensors.get(`image.field.${name}`) as Uint8Array,
      { name: `field.${name}`, width: inp, height: out, channels: 1, levels: 2 ** quant.field },
      job.what,
    );
    floats[`field.${name}`] = dequantizeWeight(
      codes as Uint8Array,
      tensors.get(`range.field.${name}`) as Float32Array,
      quant.field,
      out,
      inp,
    );
  }
  return { attributes, floats, ms: performance.now() - start };
}

self.onmessage = async (event: MessageEvent) => {
  const msg = event.data as { init?: string; job?: DecodeJob };
  if (msg.init) {
    ready = initJxl({ module_or_path: msg.init });
    return;
  }
  const job = msg.job!;
  try {
    await ready;
    const out = run(job);
    const transfer = [...Object.values(out.attributes), ...Object.values(out.floats)].flatMap((a) =>
      a ? [a.buffer as ArrayBuffer] : [],
    );
    self.postMessage({ id: job.id, ok: out }, { transfer });
  } catch (err) {
    const message = err instanceof Error ? err.message : String(err);
    self.postMessage({ id: job.id, error: message, kind: err instanceof SegmentError ? "segment" : "decode" });
  }
};
