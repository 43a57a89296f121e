// The keyframe and static-layer segments (stgs/codec/keyframe.py, stgs/codec/static.py): a safetensors file,
// checked against what the manifest announced (size, metadata, tensor names, dtypes, shapes, byte ranges,
// finite floats) before anything in it is decoded. Parsing it evaluates nothing.
import { SegmentError } from "./errors";
import { MAX_KEYFRAME_HEADER_BYTES } from "./limits";
import type { SceneShape } from "./manifest";

export const FEATURE_DIM = 16;
export const HIDDEN = 64;

export interface AttributeSpec {
  name: string;
  channels: number;
  levels: number;
}

/** The five attribute images in container order (stgs/codec/attributes.py SPECS). */
export const SPECS: AttributeSpec[] = [
  { name: "position", channels: 3, levels: 1 << 16 },
  { name: "scale", channels: 3, levels: 1 << 6 },
  { name: "rotation", channels: 4, levels: 1 << 7 },
  { name: "opacity", channels: 1, levels: 1 << 6 },
  { name: "color", channels: 3, levels: 1 << 16 },
];
export const SH1_SPECS: AttributeSpec[] = ["x", "y", "z"].map((a) => ({
  name: `sh1_${a}`,
  channels: 3,
  levels: 1 << 16,
}));

/** The decoded attributes of a keyframe or static layer: SPECS' five, and SH1_SPECS' where the layer has them. */
export type Attributes = Record<"position" | "scale" | "rotation" | "opacity" | "color", Float32Array> &
  Partial<Record<string, Float32Array>>;

/** `decoded` (attribute name -> floats) as Attributes, once each of SPECS' names is there (SegmentError if not). */
export function asAttributes(decoded: Record<string, Float32Array>, what: string): Attributes {
  const { position, scale, rotation, opacity, color } = decoded;
  if (!position || !scale || !rotation || !opacity || !color)
    throw new SegmentError(`${what}: an attribute is missing`);
  return { ...decoded, position, scale, rotation, opacity, color };
}

/** The deformation field's weights (name -> [out, in]); stgs/model/gop.py DeformationField. */
export function fieldShapes(window: number, peFreqs: number): Record<string, [number, number]> {
  return {
    "temporal.weight": [HIDDEN, window * FEATURE_DIM + 2 * peFreqs],
    "d_pos.0.weight": [HIDDEN, HIDDEN],
    "d_pos.2.weight": [3, HIDDEN],
    "d_cov.0.weight": [HIDDEN, HIDDEN],
    "d_cov.2.weight": [7, HIDDEN],
    "d_opacity.0.weight": [HIDDEN, HIDDEN + 3],
    "d_opacity.2.weight": [1, HIDDEN],
    "d_color.0.weight": [HIDDEN, HIDDEN + 3],
    "d_color.2.weight": [3, HIDDEN],
  };
}

/** How coarsely a keyframe Representation stores its images and weights (stgs/codec/quant.py KeyframeQuant): bits of
 * each attribute image (at most LOSSLESS's) and of the deformation weights (FLOAT_FIELD_BITS: float32; else per-row
 * codes in a one-channel JPEG XL image). */
export interface KeyframeQuant {
  position: number;
  scale: number;
  rotation: number;
  opacity: number;
  color: number;
  field: number;
}

export const FLOAT_FIELD_BITS = 32;
export const MAX_FIELD_BITS = 8;
export const LOSSLESS: KeyframeQuant = {
  position: 16,
  scale: 6,
  rotation: 7,
  opacity: 6,
  color: 16,
  field: FLOAT_FIELD_BITS,
};
const QUANT_KEYS = ["position", "scale", "rotation", "opacity", "color", "field"] as const;

export function isLossless(q: KeyframeQuant): boolean {
  return QUANT_KEYS.every((k) => q[k] === LOSSLESS[k]);
}

/** `position=12;scale=5;...;field=8`: the manifest's and the segment's spelling. */
export function quantValue(q: KeyframeQuant): string {
  return QUANT_KEYS.map((k) => `${k}=${q[k]}`).join(";");
}

/** The quantisation a descriptor value spells (every key once, bits in range), else an Error naming the field. */
export function parseQuant(value: string): KeyframeQuant {
  const items = value.split(";").map((part) => part.split("="));
  const got = new Map(items.map(([k, v]) => [k, v]));
  if (items.length !== QUANT_KEYS.length || got.size !== QUANT_KEYS.length || !QUANT_KEYS.every((k) => got.has(k))) {
    throw new Error(`quant must name ${QUANT_KEYS.join(", ")} once each, got ${JSON.stringify(value.slice(0, 80))}`);
  }
  const q = { ...LOSSLESS };
  for (const k of QUANT_KEYS) {
    const raw = got.get(k) ?? "";
    if (!/^\d{1,2}$/.test(raw))
      throw new Error(`quant bits must be integers, got ${JSON.stringify(value.slice(0, 80))}`);
    const bits = Number(raw);
    const ok =
      k === "field"
        ? bits === FLOAT_FIELD_BITS || (bits >= 2 && bits <= MAX_FIELD_BITS)
        : bits >= 1 && bits <= LOSSLESS[k];
    if (!ok) throw new Error(`quant ${k}=${bits} is out of range`);
    q[k] = bits;
  }
  return q;
}

/** The attribute images at a keyframe Representation's levels. */
export function quantSpecs(q: KeyframeQuant): AttributeSpec[] {
  return SPECS.map((s) => ({ ...s, levels: 2 ** q[s.name as keyof KeyframeQuant] }));
}

/** name -> shape (null: a JPEG XL byte string) of a keyframe segment at quantisation `quant`. */
export function keyframeTensors(shape: SceneShape, quant: KeyframeQuant = LOSSLESS): Map<string, number[] | null> {
  const want = imageTensors(SPECS);
  want.set("range.features", [2, FEATURE_DIM]);
  for (const [name, s] of Object.entries(fieldShapes(shape.window, shape.peFreqs))) {
    if (quant.field === FLOAT_FIELD_BITS) {
      want.set(`field.${name}`, s);
    } else {
      want.set(`image.field.${name}`, null);
      want.set(`range.field.${name}`, [2, s[0]]);
    }
  }
  return want;
}

export function imageTensors(specs: AttributeSpec[]): Map<string, number[] | null> {
  const want = new Map<string, number[] | null>();
  for (const s of specs) {
    want.set(`image.${s.name}`, null);
    want.set(`range.${s.name}`, [2, s.channels]);
  }
  return want;
}

export function keyframeMetadata(
  gop: number,
  shape: SceneShape,
  quant: KeyframeQuant = LOSSLESS,
): Record<string, string> {
  const meta: Record<string, string> = {
    format: "streamstgs-keyframe",
    version: "1",
    gop: String(gop),
    grid_side: String(shape.side),
    capacity: String(shape.capacity),
    gop_size: String(shape.gopSize),
    window: String(shape.window),
    pe_freqs: String(shape.peFreqs),
    feature_bits: "12",
  };
  if (!isLossless(quant)) meta.quant = quantValue(quant);
  return meta;
}

export function staticMetadata(capacity: number, side: number, shDegree: number): Record<string, string> {
  return {
    format: "streamstgs-static",
    version: "1",
    capacity: String(capacity),
    grid_side: String(side),
    sh_degree: String(shDegree),
  };
}

export type Tensors = Map<string, Uint8Array | Float32Array>;

/** The segment's tensors: JPEG XL byte strings as Uint8Array views, floats copied into Float32Arrays. */
export function readContainer(
  data: ArrayBuffer,
  metadata: Record<string, string>,
  want: Map<string, number[] | null>,
  maxBytes: number,
  what: string,
): Tensors {
  const fail = (m: string): never => {
    throw new SegmentError(`${what} ${m}`);
  };
  if (data.byteLength > maxBytes) fail(`segment is ${data.byteLength} bytes, over the ${maxBytes}-byte limit`);
  if (data.byteLength < 8) fail("segment is truncated");
  const view = new DataView(data);
  const size = Number(view.getBigUint64(0, true));
  if (size > MAX_KEYFRAME_HEADER_BYTES || 8 + size > data.byteLength) fail(`header claims ${size} bytes`);
  let header: Record<string, unknown>;
  try {
    header = JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(new Uint8Array(data, 8, size)));
  } catch (e) {
    return fail(`header is not JSON (${e instanceof Error ? e.message : e})`);
  }
  if (typeof header !== "object" || header === null || Array.isArray(header)) fail("header is not a JSON object");
  let meta: Record<string, unknown> = {};
  try {
    const m = (header.__metadata__ as Record<string, unknown> | undefined)?.streamstgs;
    meta = typeof m === "string" ? JSON.parse(m) : {};
  } catch {
    fail("metadata is not JSON");
  }
  for (const [key, value] of Object.entries(metadata)) {
    if (meta[key] !== value) fail(`${key} is ${JSON.stringify(meta[key])}, expected ${JSON.stringify(value)}`);
  }
  const extra = Object.keys(meta)
    .filter((k) => !(k in metadata))
    .sort();
  if (extra.length) fail(`metadata has unexpected keys ${JSON.stringify(extra)}`);
  const names = Object.keys(header).filter((k) => k !== "__metadata__");
  const missing = [...want.keys()].filter((k) => !names.includes(k));
  const unknown = names.filter((k) => !want.has(k));
  if (missing.length || unknown.length) fail(`tensors differ from the format (missing ${missing}, unknown ${unknown})`);
  const body = 8 + size;
  const tensors: Tensors = new Map();
  for (const [name, shape] of want) {
    const entry = header[name] as { dtype?: unknown; shape?: unknown; data_offsets?: unknown };
    const dtype = shape === null ? "U8" : "F32";
    if (typeof entry !== "object" || entry === null || entry.dtype !== dtype) fail(`tensor ${name} must be ${dtype}`);
    const offsets = entry.data_offsets;
    if (
      !Array.isArray(offsets) ||
      offsets.length !== 2 ||
      !offsets.every((o) => Number.isSafeInteger(o) && o >= 0) ||
      offsets[0] > offsets[1] ||
      body + offsets[1] > data.byteLength
    )
      fail(`tensor ${name} has bad byte offsets`);
    const [start, end] = offsets as [number, number];
    if (shape === null) {
      if (!Array.isArray(entry.shape) || entry.shape.length !== 1 || entry.shape[0] !== end - start)
        fail(`tensor ${name} shape does not match its bytes`);
      tensors.set(name, new Uint8Array(data, body + start, end - start));
    } else {
      if (!Array.isArray(entry.shape) || entry.shape.join(",") !== shape.join(",")) {
        fail(`tensor ${name} has shape ${JSON.stringify(entry.shape)}, expected [${shape}]`);
      }
      const count = shape.reduce((a, b) => a * b, 1);
      if (end - start !== count * 4) fail(`tensor ${name} has ${end - start} bytes, expected ${count * 4}`);
      const floats = new Float32Array(count);
      const dv = new DataView(data, body + start, end - start);
      for (let i = 0; i < count; i++) {
        const v = dv.getFloat32(4 * i, true);
        if (!Number.isFinite(v)) fail(`tensor ${name} contains NaN or Inf`);
        floats[i] = v;
      }
      tensors.set(name, floats);
    }
  }
  return tensors;
}

/** Codes (S*S*C, row-major interleaved) -> float32 values: unit = code / (levels - 1); lo + unit * (hi - lo). */
export function dequantize(spec: AttributeSpec, codes: Uint8Array | Uint16Array, range: Float32Array): Float32Array {
  const out = new Float32Array(codes.length);
  const c = spec.channels;
  const f = Math.fround;
  const denom = f(spec.levels - 1);
  for (let i = 0; i < codes.length; i++) {
    const code = codes[i]!;
    if (code >= spec.levels) throw new SegmentError(`${spec.name}: code ${code} exceeds ${spec.levels - 1}`);
    const ch = i % c;
    const lo = range[ch]!;
    out[i] = f(f(f(code / denom) * f(range[c + ch]! - lo)) + lo);
  }
  return out;
}

/** Per-row weight codes (out x in, row-major) -> float32 weights: unit = code / (2^bits - 1); lo + unit * (hi - lo)
 * with row r's [lo, hi] = range[r], range[out + r] (stgs/codec/keyframe.py dequantize_weight). */
export function dequantizeWeight(
  codes: Uint8Array,
  range: Float32Array,
  bits: number,
  out: number,
  inp: number,
): Float32Array {
  const f = Math.fround;
  const levels = 2 ** bits - 1;
  const denom = f(levels);
  const w = new Float32Array(out * inp);
  for (let r = 0; r < out; r++) {
    const lo = range[r]!;
    const span = f(range[out + r]! - lo);
    for (let c = 0; c < inp; c++) {
      const code = codes[r * inp + c]!;
      if (code > levels) throw new SegmentError(`weight code ${code} exceeds ${levels}`);
      w[r * inp + c] = f(f(f(code / denom) * span) + lo);
    }
  }
  return w;
}
