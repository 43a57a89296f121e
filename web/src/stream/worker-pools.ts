// The main thread's side of the decoder workers: a pool of keyframe (JPEG XL) decoders and the feature decoder.
import type { DecodeJob, DecodedSegment } from "../workers/keyframe.worker";
import { SegmentError, UnsupportedError } from "../errors";

export interface Assets {
  jxl: string;
  "keyframe.worker": string;
  "feature.worker": string;
  "sort.worker": string;
}

function moduleWorker(url: string): Worker {
  return new Worker(new URL(url, document.baseURI), { type: "module" });
}

export class KeyframePool {
  private readonly workers: Worker[];
  private readonly busy: number[];
  private readonly pending = new Map<
    number,
    { resolve: (d: DecodedSegment) => void; reject: (e: Error) => void; worker: number }
  >();
  private next = 0;

  constructor(assets: Assets, size: number) {
    const wasm = new URL(assets.jxl, document.baseURI).href;
    this.workers = Array.from({ length: size }, (_, i) => {
      const w = moduleWorker(assets["keyframe.worker"]);
      w.postMessage({ init: wasm });
      w.onmessage = (e) => this.settle(e.data, i);
      return w;
    });
    this.busy = this.workers.map(() => 0);
  }

  private settle(msg: { id: number; ok?: DecodedSegment; error?: string }, worker: number): void {
    const job = this.pending.get(msg.id);
    if (!job) return;
    this.pending.delete(msg.id);
    this.busy[worker]!--;
    if (msg.ok) job.resolve(msg.ok);
    else job.reject(new SegmentError(msg.error ?? "decode failed"));
  }

  decode(job: Omit<DecodeJob, "id">): Promise<DecodedSegment> {
    const id = this.next++;
    let w = 0;
    for (let i = 1; i < this.workers.length; i++) if (this.busy[i]! < this.busy[w]!) w = i;
    this.busy[w]!++;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject, worker: w });
      this.workers[w]!.postMessage({ job: { ...job, id } }, [job.data]);
    });
  }

  terminate(): void {
    for (const w of this.workers) w.terminate();
  }
}

export interface FeatureFrame {
  gop: number;
  rung: number;
  index: number;
  data: Uint16Array<ArrayBuffer>;
  copyMs: number;
}

export class FeatureDecoder {
  private readonly worker: Worker;
  onFrame: (f: FeatureFrame) => void = () => undefined;
  onError: (gop: number, e: Error) => void = () => undefined;

  constructor(assets: Assets) {
    this.worker = moduleWorker(assets["feature.worker"]);
    this.worker.onmessage = (e) => {
      const m = e.data;
      if (m.type === "frame") this.onFrame(m);
      else if (m.type === "error")
        this.onError(m.gop, new SegmentError(`feature segment of GOP ${m.gop}: ${m.message}`));
      else if (m.type === "unsupported") this.onError(-1, new UnsupportedError(m.message));
    };
  }

  open(gop: number, rung: number, side: number, frames: number, codec: string, init: ArrayBuffer): void {
    this.worker.postMessage({ type: "open", gop, rung, side, frames, codec, init: init.slice(0) });
  }

  chunk(gop: number, data: Uint8Array | null, last: boolean): void {
    const copy = data ? data.slice().buffer : new ArrayBuffer(0);
    this.worker.postMessage({ type: "chunk", gop, data: copy, last }, [copy]);
  }

  credit(n: number): void {
    if (n > 0) this.worker.postMessage({ type: "credit", n });
  }

  reset(): void {
    this.worker.postMessage({ type: "reset" });
  }

  terminate(): void {
    this.worker.terminate();
  }
}

export class Sorter {
  private readonly worker: Worker;
  private next = 0;
  private readonly pending = new Map<number, (r: { order: Uint32Array; ms: number }) => void>();

  constructor(assets: Assets) {
    this.worker = moduleWorker(assets["sort.worker"]);
    this.worker.onmessage = (e) => {
      const done = this.pending.get(e.data.id);
      this.pending.delete(e.data.id);
      done?.(e.data);
    };
  }

  setStatic(positions: Float32Array): void {
    this.worker.postMessage({ type: "static", positions });
  }

  sort(
    positions: Float32Array,
    view: ArrayLike<number>,
    guard: [number, number, number],
  ): Promise<{ order: Uint32Array; ms: number }> {
    const id = this.next++;
    return new Promise((resolve) => {
      this.pending.set(id, resolve);
      this.worker.postMessage({ type: "sort", id, positions, view: Array.from(view), guard }, [positions.buffer]);
    });
  }

  terminate(): void {
    this.worker.terminate();
  }
}
