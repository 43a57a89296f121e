// The static layer (model format 2): fetched once per Period, whatever the start GOP, decoded in a keyframe
// worker; the sort worker gets its (mean, opacity) here, the splat pass its attributes (as textures, which the
// player makes: the stream builds nothing on the GPU).
import { type Attributes, SH1_SPECS, SPECS, imageTensors, staticMetadata } from "../container";
import { type Manifest, segmentCap } from "../manifest";
import { fetchStream } from "./fetch";
import type { KeyframePool, Sorter } from "./worker-pools";

/** The decoded static layer: its attributes on a `side` x `side` grid, and the decode time. */
export interface StaticLayer {
  attributes: Attributes;
  capacity: number;
  side: number;
  shDegree: number;
  ms: number;
}

/** Fetch and decode the manifest's static layer, and hand its (mean, opacity) to the sorter. */
export async function loadStaticLayer(m: Manifest, keyframes: KeyframePool, sorter: Sorter): Promise<StaticLayer> {
  const s = m.staticLayer!;
  const maxBytes = segmentCap(s.bandwidth, m.durationS);
  const got = await fetchStream(s.url, m.policy, maxBytes, "static-layer segment", null);
  const specs = s.shDegree ? [...SPECS, ...SH1_SPECS] : SPECS;
  const decoded = await keyframes.decode({
    data: got.data,
    what: "static-layer",
    metadata: staticMetadata(s.capacity, s.side, s.shDegree),
    want: [...imageTensors(specs)],
    side: s.side,
    shDegree: s.shDegree,
    maxBytes,
  });
  const attrs = decoded.attributes;
  const positions = new Float32Array(4 * s.capacity);
  for (let i = 0; i < s.capacity; i++) {
    positions.set(attrs.position.subarray(3 * i, 3 * i + 3), 4 * i);
    positions[4 * i + 3] = 1 / (1 + Math.exp(-attrs.opacity[i]!));
  }
  sorter.setStatic(positions);
  return { attributes: attrs, capacity: s.capacity, side: s.side, shDegree: s.shDegree, ms: decoded.ms };
}
