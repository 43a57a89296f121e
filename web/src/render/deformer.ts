// Which ring slot on the GPU holds which feature frame (gop, e): a frame is uploaded once, when a frame first
// needs it, into the slot used longest ago.
import { type Attributes, fieldShapes } from "../container";

export class LayerRing {
  private readonly slotOf = new Map<string, number>();
  private next = 0;

  constructor(
    readonly slots: number,
    private readonly upload: (slot: number, codes: Uint16Array) => void,
  ) {}

  slot(gop: number, e: number, codes: () => Uint16Array): number {
    const key = `${gop}:${e}`;
    const have = this.slotOf.get(key);
    if (have !== undefined) return have;
    const slot = this.next;
    this.next = (this.next + 1) % this.slots;
    for (const [k, v] of this.slotOf) if (v === slot) this.slotOf.delete(k);
    this.upload(slot, codes());
    this.slotOf.set(key, slot);
    return slot;
  }

  forget(): void {
    this.slotOf.clear();
  }
}

/** What the player needs of a deformation back end (WebGL2 fragment shader or WebGPU compute). */
export interface Deformer {
  /** What runs it, for the stats and the benchmark. */
  readonly kind: string;
  /** The deformed dynamic layer as the splat pass reads it: (mean, opacity), scale, quaternion, colour. */
  readonly outputs: WebGLTexture[];
  loadGop(attributes: Attributes, floats: Record<string, Float32Array>): void;
  /** The slot holding feature frame `e` of `gop` (uploaded from `codes` when not resident). */
  layer(gop: number, e: number, codes: () => Uint16Array): number;
  forget(): void;
  /** Deform frame `frame` seen from `camera` (its centre); resolves to every Gaussian's (mean, opacity). */
  deform(frame: number, layers: number[], camera: ArrayLike<number>): Promise<Float32Array>;
  /** Wait for the GPU (timing only). */
  sync(): void;
}

/** γ(t) of frame `frame` (stgs/model/gop.py positional_encoding in float32), padded to whole vec4s. */
export function positionalEncoding(frame: number, gopSize: number, peFreqs: number): Float32Array {
  const t = gopSize > 1 ? frame / (gopSize - 1) : 0;
  const pe = new Float32Array(Math.max(4, 4 * Math.ceil((2 * peFreqs) / 4)));
  for (let k = 0; k < peFreqs; k++) {
    const angle = Math.fround(Math.fround(Math.fround(2 ** k) * Math.fround(Math.PI)) * Math.fround(t));
    pe[k] = Math.sin(angle);
    pe[peFreqs + k] = Math.cos(angle);
  }
  return pe;
}

/** (lo, step) per channel of the 10-bit codes: value = code * step + lo (stgs/codec/features.py). */
export function dequantisation(ranges: Float32Array, codeMax: number): [Float32Array, Float32Array] {
  const lo = new Float32Array(16);
  const step = new Float32Array(16);
  for (let c = 0; c < 16; c++) {
    lo[c] = ranges[c]!;
    step[c] = Math.fround(Math.fround(ranges[16 + c]! - ranges[c]!) / codeMax);
  }
  return [lo, step];
}

export const WEIGHT_TEXTURE_WIDTH = 1024;
export const CODE_MAX = 1023;

/** The deformation weights packed into RGBA32F texels, each matrix row padded to whole texels. */
export interface Packed {
  texels: Float32Array;
  /** matrix name -> [first texel, texels per row] */
  offsets: Record<string, [number, number]>;
}

export function packWeights(floats: Record<string, Float32Array>, window: number, peFreqs: number): Packed {
  const shapes = fieldShapes(window, peFreqs);
  const offsets: Record<string, [number, number]> = {};
  let texels = 0;
  for (const [name, [rows, cols]] of Object.entries(shapes)) {
    offsets[name] = [texels, Math.ceil(cols / 4)];
    texels += rows * Math.ceil(cols / 4);
  }
  const height = Math.ceil(texels / WEIGHT_TEXTURE_WIDTH);
  const data = new Float32Array(WEIGHT_TEXTURE_WIDTH * height * 4);
  for (const [name, [rows, cols]] of Object.entries(shapes)) {
    const w = floats[`field.${name}`]!;
    const [first, per] = offsets[name]!;
    for (let r = 0; r < rows; r++) for (let c = 0; c < cols; c++) data[4 * (first + r * per) + c] = w[r * cols + c]!;
  }
  return { texels: data, offsets };
}
