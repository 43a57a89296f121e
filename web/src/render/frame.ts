// One frame on the GPU, the presentation half of the player: the GOP's dynamic layer deformed from the frame's
// feature window, every Gaussian depth-ordered (the sort runs in a worker, behind `sort`), the static and
// dynamic layers splatted together (a still scene: the static layer alone, StillFrame). The player decides which
// frame and when (clock, seeks, stalls).
import { type View, cameraCenter } from "../camera";
import type { Attributes } from "../container";
import { guardLimits } from "../sort";
import type { Deformer } from "./deformer";
import type { SplatPass, StaticTextures } from "./splat";

/** The depth order of (mean, opacity) rows for a view's matrix and guard band; `ms`: the worker's own time. */
export type SortFn = (
  means: Float32Array,
  viewmat: ArrayLike<number>,
  guard: [number, number, number],
) => Promise<{ order: Uint32Array; ms: number }>;

/** Where one frame's time went (ms). */
export interface FrameTimes {
  deform: number;
  /** The sort worker's own time. */
  sort: number;
  /** From sending the means to the sort worker to getting the order back. */
  sortWait: number;
  draw: number;
  /** Gaussians drawn. */
  visible: number;
}

export class FramePipeline {
  private loadedGop = -1;

  constructor(
    readonly deformer: Deformer,
    private readonly splat: SplatPass,
    private readonly sort: SortFn,
    readonly staticLayer: StaticTextures | null,
    private readonly side: number,
    private readonly background: [number, number, number],
    /** After each draw, wait for the GPU (exact per-stage times, for benchmarks). */
    private readonly syncTiming: boolean,
  ) {}

  /** Whether GOP k's keyframe is the one loaded on the GPU. */
  holds(k: number): boolean {
    return this.loadedGop === k;
  }

  /** Drop the GOP and feature frames held on the GPU (a seek). */
  forget(): void {
    this.deformer.forget();
    this.loadedGop = -1;
  }

  /** Frame i of GOP k seen from `view`: `keyframe` is the GOP's decoded keyframe, `codes(e)` feature frame e's
   * codes (uploaded only when the GPU does not hold them). */
  async draw(
    k: number,
    i: number,
    window: number,
    keyframe: { attributes: Attributes; floats: Record<string, Float32Array> },
    codes: (e: number) => Uint16Array,
    view: View,
  ): Promise<FrameTimes> {
    if (this.loadedGop !== k) {
      this.deformer.loadGop(keyframe.attributes, keyframe.floats);
      this.loadedGop = k;
    }
    const t0 = performance.now();
    const layers = Array.from({ length: window }, (_, j) => this.deformer.layer(k, i + j, () => codes(i + j)));
    const means = await this.deformer.deform(i, layers, cameraCenter(view.viewmat));
    const t1 = performance.now();
    const [fx, , cx, fy, cy] = view.K;
    const { order, ms } = await this.sort(means, view.viewmat, guardLimits(fx, cx, fy, cy, view.width, view.height));
    const t2 = performance.now();
    this.splat.draw(view, order, order.length, this.staticLayer, this.deformer.outputs, this.side, this.background);
    if (this.syncTiming) this.deformer.sync();
    const t3 = performance.now();
    return { deform: t1 - t0, sort: ms, sortWait: t2 - t1, draw: t3 - t2, visible: order.length };
  }
}

/** A still scene's frame (the static layer alone): depth-ordered, splatted; no deformation, no GOP. */
export class StillFrame {
  constructor(
    private readonly splat: SplatPass,
    private readonly sort: SortFn,
    readonly staticLayer: StaticTextures,
    private readonly background: [number, number, number],
    /** After each draw, wait for the GPU (exact per-stage times, for benchmarks). */
    private readonly syncTiming: boolean,
  ) {}

  async draw(view: View): Promise<FrameTimes> {
    const [fx, , cx, fy, cy] = view.K;
    const t1 = performance.now();
    const guard = guardLimits(fx, cx, fy, cy, view.width, view.height);
    const { order, ms } = await this.sort(new Float32Array(0), view.viewmat, guard);
    const t2 = performance.now();
    this.splat.draw(view, order, order.length, this.staticLayer, [], 1, this.background);
    if (this.syncTiming) this.splat.sync();
    return { deform: 0, sort: ms, sortWait: t2 - t1, draw: performance.now() - t2, visible: order.length };
  }
}
