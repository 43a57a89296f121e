// The depth sort, off the main thread: the static layer's positions arrive once, each frame's deformed dynamic
// positions per frame; the order goes back as a transferable Uint32Array.
import { depthOrder, type SortScratch } from "../sort";

let staticLayer: Float32Array<ArrayBuffer> = new Float32Array(0);
let scratch: SortScratch | null = null;

self.onmessage = (event: MessageEvent) => {
  const msg = event.data as {
    type: string;
    id: number;
    positions: Float32Array<ArrayBuffer>;
    view: number[];
    guard: [number, number, number];
  };
  if (msg.type === "static") {
    staticLayer = msg.positions;
    return;
  }
  const start = performance.now();
  const [ids, s] = depthOrder([staticLayer, msg.positions], msg.view, msg.guard, scratch);
  scratch = s;
  const order = ids.slice();
  self.postMessage({ id: msg.id, order, ms: performance.now() - start }, { transfer: [order.buffer] });
};
