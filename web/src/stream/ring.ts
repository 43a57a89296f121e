// The bounded ring of decoded feature frames just ahead of the renderer (docs/CLIENT.md's pipeline): at most
// `capacity` frames are held or being decoded; the decoder gets one credit back for every frame the renderer
// is done with (or that arrives already stale, after a drop or a seek).
import type { FeatureDecoder, FeatureFrame } from "./worker-pools";

export class FeatureRing {
  private readonly frames = new Map<number, Map<number, Uint16Array>>();
  /** (gop, first feature index) still needed: everything before it is released. */
  private keepGop = 0;
  private keepIndex = 0;
  copyMs = 0;

  constructor(
    private readonly decoder: FeatureDecoder,
    readonly capacity: number,
  ) {}

  start(gop: number): void {
    this.frames.clear();
    this.keepGop = gop;
    this.keepIndex = 0;
    this.decoder.credit(this.capacity);
  }

  private stale(gop: number, index: number): boolean {
    return gop < this.keepGop || (gop === this.keepGop && index < this.keepIndex);
  }

  add(f: FeatureFrame): void {
    this.copyMs = f.copyMs;
    if (this.stale(f.gop, f.index)) {
      this.decoder.credit(1);
      return;
    }
    let gop = this.frames.get(f.gop);
    if (!gop) {
      gop = new Map();
      this.frames.set(f.gop, gop);
    }
    gop.set(f.index, f.data);
  }

  get(gop: number, index: number): Uint16Array | undefined {
    return this.frames.get(gop)?.get(index);
  }

  has(gop: number, first: number, count: number): boolean {
    const g = this.frames.get(gop);
    if (!g) return false;
    for (let e = first; e < first + count; e++) if (!g.has(e)) return false;
    return true;
  }

  /** Release every frame before feature `index` of `gop` (and all earlier GOPs). */
  release(gop: number, index: number): void {
    this.keepGop = gop;
    this.keepIndex = index;
    let freed = 0;
    for (const [k, g] of this.frames) {
      for (const e of [...g.keys()]) {
        if (this.stale(k, e)) {
          g.delete(e);
          freed++;
        }
      }
      if (!g.size) this.frames.delete(k);
    }
    this.decoder.credit(freed);
  }

  get held(): number {
    let n = 0;
    for (const g of this.frames.values()) n += g.size;
    return n;
  }
}
