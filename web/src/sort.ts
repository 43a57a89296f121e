// The depth order of one frame (docs/ARCHITECTURE.md, splatter rules 1, 4 and 5): cull Gaussians whose opacity cannot reach 1/255
// or whose mean lies outside the guard band (stgs/model/renderer.py, the model's drawing rule: deeper than 0.2 and
// projecting within 1.3x the image's half-extent; it also covers the splatter's 0.01 near cut), then order the
// rest front to back by the depth of the mean.
// An LSD radix sort on the depth's float bits (positive floats order as their bit patterns): exact, stable
// (ties keep index order) and linear in N.
export const NEAR_CLIP = 0.2;
export const GUARD_BAND = 1.3;

/** [near, x limit, y limit] of the guard band for intrinsics (fx, cx, fy, cy) and an image size (guard_limits). */
export function guardLimits(
  fx: number,
  cx: number,
  fy: number,
  cy: number,
  width: number,
  height: number,
): [number, number, number] {
  return [NEAR_CLIP, (GUARD_BAND * Math.max(cx, width - cx)) / fx, (GUARD_BAND * Math.max(cy, height - cy)) / fy];
}
export const ALPHA_MIN = 1 / 255;

export interface SortScratch {
  keys: Uint32Array;
  ids: Uint32Array;
  keys2: Uint32Array;
  ids2: Uint32Array;
}

function scratch(n: number, s: SortScratch | null): SortScratch {
  if (s && s.keys.length >= n) return s;
  return { keys: new Uint32Array(n), ids: new Uint32Array(n), keys2: new Uint32Array(n), ids2: new Uint32Array(n) };
}

const f32 = new Float32Array(1);
const u32 = new Uint32Array(f32.buffer);

/** Append the visible Gaussians of `layer` ((x, y, z, opacity) per Gaussian) as (depth bits, base + index). */
function collect(
  layer: Float32Array,
  base: number,
  view: ArrayLike<number>,
  guard: [number, number, number],
  s: SortScratch,
  n: number,
): number {
  const [r0, r1, r2, t] = [view[8]!, view[9]!, view[10]!, view[11]!];
  const [near, lx, ly] = guard;
  for (let i = 0, count = layer.length / 4; i < count; i++) {
    const o = layer[4 * i + 3]!;
    if (!(o * 255 >= 1)) continue;
    const [x, y, w] = [layer[4 * i]!, layer[4 * i + 1]!, layer[4 * i + 2]!];
    const z = r0 * x + r1 * y + r2 * w + t;
    if (!(z > near)) continue;
    if (Math.abs(view[0]! * x + view[1]! * y + view[2]! * w + view[3]!) > lx * z) continue;
    if (Math.abs(view[4]! * x + view[5]! * y + view[6]! * w + view[7]!) > ly * z) continue;
    f32[0] = z;
    s.keys[n] = u32[0]!;
    s.ids[n++] = base + i;
  }
  return n;
}

/** Front-to-back order of the visible Gaussians of both layers (static first in index space), under `view`
 * (world-to-camera, row-major 4x4) and guard band. Returns the ids (a view into scratch) and the scratch to reuse. */
export function depthOrder(
  layers: Float32Array[],
  view: ArrayLike<number>,
  guard: [number, number, number],
  prev: SortScratch | null,
): [Uint32Array, SortScratch] {
  const total = layers.reduce((a, l) => a + l.length / 4, 0);
  let s = scratch(total, prev);
  let n = 0;
  let base = 0;
  for (const layer of layers) {
    n = collect(layer, base, view, guard, s, n);
    base += layer.length / 4;
  }
  const counts = new Uint32Array(2048);
  let [ka, ia, kb, ib] = [s.keys, s.ids, s.keys2, s.ids2];
  for (let shift = 0; shift < 32; shift += 11) {
    counts.fill(0);
    for (let i = 0; i < n; i++) counts[(ka[i]! >>> shift) & 2047]!++;
    let sum = 0;
    for (let b = 0; b < 2048; b++) {
      const c = counts[b]!;
      counts[b] = sum;
      sum += c;
    }
    for (let i = 0; i < n; i++) {
      const dst = counts[(ka[i]! >>> shift) & 2047]!++;
      kb[dst] = ka[i]!;
      ib[dst] = ia[i]!;
    }
    [ka, kb] = [kb, ka];
    [ia, ib] = [ib, ia];
  }
  s = { keys: ka, ids: ia, keys2: kb, ids2: ib };
  return [ia.subarray(0, n), s];
}
