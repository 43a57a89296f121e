// The download loop (stgs/client/fetch/schedule.py's order of work, in the page): for each GOP from the start GOP on, wait
// for room in the buffer, let the ABR rule choose the rung (its features and the keyframe Representation it pairs
// with; the cheapest keyframes are budgeted apart), fetch the rung's init segment once, then its keyframe and media
// segment together; the media
// bytes stream into the feature decoder as they arrive, the keyframe goes to a decoder worker at once (the next
// GOP's keyframe is pre-decoded while the current one plays). One throughput sample per GOP (both bodies).
import type { AbrRule, AbrSettings, AbrState, Decision, ThroughputSample, UpcomingGOP } from "../abr/state";
import { FixedRule } from "../abr/rules";
import { FLOAT_FIELD_BITS, fieldShapes, keyframeMetadata, keyframeTensors } from "../container";
import { MAX_INIT_BYTES } from "../limits";
import { KEYFRAME_REP, type KeyframeRep, type Manifest } from "../manifest";
import type { DecodedSegment } from "../workers/keyframe.worker";
import { fetchStream } from "./fetch";
import type { FeatureDecoder, KeyframePool } from "./worker-pools";

export interface GopDownload {
  gop: number;
  rung: number;
  decision: Decision;
  keyframe: Promise<DecodedSegment>;
  bytes: number;
  seconds: number;
}

/** A downloaded GOP in the player, with its keyframe once decoded. */
export interface GopState {
  download: GopDownload;
  decoded: DecodedSegment | null;
}

export interface DownloaderHooks {
  /** Seconds of media played so far (the playhead). */
  playheadS(): number;
  playing(): boolean;
  onGop(d: GopDownload): void;
  onError(err: Error): void;
}

/** GOP k's keyframe and per-rung feature bits and PSNR from stats.json (stgs/client/abr/state.py UpcomingGOP.from_stats):
 * each rung's keyframes are those of `keyframeReps` (its @associationId); the cheapest are the keyframe bits, what a
 * rung's cost beyond them counts to its segment bits. */
export function upcomingFromStats(
  stats: unknown,
  k: number,
  repIds: string[],
  keyframeReps: string[],
): UpcomingGOP | null {
  try {
    const gop = (stats as { gops: Record<string, unknown>[] }).gops[k] as {
      index: number;
      keyframe_bytes: number;
      keyframes?: Record<string, number>;
      representations: Record<string, { bytes: number; render_psnr?: number; truth_psnr?: number }>;
    };
    if (gop.index !== k) return null;
    const paired = keyframeReps.map(
      (rep) => Number(rep === KEYFRAME_REP ? gop.keyframe_bytes : gop.keyframes![rep]) * 8,
    );
    const features = repIds.map((r) => Number(gop.representations[r]!.bytes) * 8);
    if (![...paired, ...features].every((v) => Number.isFinite(v) && v > 0)) return null;
    const keyframeBits = Math.min(...paired);
    const segmentBits = features.map((f, i) => f + paired[i]! - keyframeBits);
    // against the capture where every rung has it, else against the uncompressed model (stgs.tree.rung_quality)
    const entries = repIds.map((r) => gop.representations[r]!);
    const truth = entries.every((e) => "truth_psnr" in e);
    let psnr: number[] | null = entries.map((e) => Number(truth ? e.truth_psnr : e.render_psnr));
    if (!psnr.every(Number.isFinite)) psnr = null;
    return { keyframeBits, segmentBits, psnr };
  } catch {
    return null;
  }
}

/** A keyframe Representation's quantised weight images, name -> [out, in] (none for float32 weights). */
function quantisedFields(m: Manifest, rep: KeyframeRep): [string, [number, number]][] {
  return rep.quant.field === FLOAT_FIELD_BITS ? [] : Object.entries(fieldShapes(m.shape.window, m.shape.peFreqs));
}

export class Downloader {
  readonly samples: ThroughputSample[] = [];
  downloadedUntilS = 0;
  current: number | null = null;
  private readonly inits = new Map<number, ArrayBuffer>();
  private abort = new AbortController();
  private generation = 0;
  private lastKeyframeBits = 0;
  pinned: number | null = null;

  constructor(
    private readonly manifest: Manifest,
    private readonly rule: AbrRule,
    private readonly settings: AbrSettings,
    private readonly features: FeatureDecoder,
    private readonly keyframes: KeyframePool,
    readonly bufferCapacityS: number,
    private readonly stats: unknown,
    private readonly hooks: DownloaderHooks,
  ) {}

  private upcoming(k: number): UpcomingGOP | null {
    const rungs = this.manifest.rungs;
    return this.stats
      ? upcomingFromStats(
          this.stats,
          k,
          rungs.map((r) => r.id),
          rungs.map((r) => r.keyframeRep),
        )
      : null;
  }

  state(k: number, waitedS: number): AbrState {
    const info = this.upcoming(k);
    const ahead: UpcomingGOP[] = [];
    for (let j = k + 1; j < this.manifest.gops && ahead.length < this.settings.mpcHorizon - 1; j++) {
      const u = this.upcoming(j);
      if (!u) break;
      ahead.push(u);
    }
    return {
      bandwidths: this.manifest.abrBandwidths(),
      segmentS: this.manifest.gopSeconds,
      bufferS: Math.max(0, this.downloadedUntilS - this.hooks.playheadS()),
      bufferCapacityS: this.bufferCapacityS,
      samples: this.samples.slice(),
      keyframeBits: info?.keyframeBits ?? this.lastKeyframeBits,
      segmentBits: info?.segmentBits ?? null,
      current: this.current,
      roundTrips: 1,
      keyframeFetched: false,
      waitedS,
      upcoming: info ? [info, ...ahead] : [],
      playing: this.hooks.playing(),
    };
  }

  /** Download from GOP `first` on (stopping whatever ran before). */
  start(first: number): void {
    this.stop();
    const generation = ++this.generation;
    this.downloadedUntilS = first * this.manifest.gopSeconds;
    void this.run(first, generation).catch((err) => {
      if (generation === this.generation && !this.abort.signal.aborted) this.hooks.onError(err);
    });
  }

  stop(): void {
    this.generation++;
    this.abort.abort();
    this.abort = new AbortController();
  }

  private async run(first: number, generation: number): Promise<void> {
    const m = this.manifest;
    const T = m.gopSeconds;
    const signal = this.abort.signal;
    let arrived = performance.now();
    for (let k = first; k < m.gops; k++) {
      while (this.downloadedUntilS - this.hooks.playheadS() + T > this.bufferCapacityS + 1e-9) {
        await new Promise((r) => setTimeout(r, 20));
        if (generation !== this.generation) return;
      }
      const waited = k === first ? 0 : Math.max(0, (performance.now() - arrived) / 1e3);
      const state = this.state(k, waited);
      const decision = this.pinned !== null ? new FixedRule(this.pinned).choose() : this.rule.choose(state);
      const rung = Math.max(0, Math.min(m.rungs.length - 1, decision.index));
      const start = performance.now();
      let init = this.inits.get(rung);
      if (!init) {
        init = (
          await fetchStream(m.initUrl(rung), m.policy, MAX_INIT_BYTES, `init segment of ${m.rungs[rung]!.id}`, signal)
        ).data;
        this.inits.set(rung, init);
      }
      if (generation !== this.generation) return;
      this.features.open(k, rung, m.shape.side, m.shape.numFeatures, m.rungs[rung]!.codecs, init);
      const kfRep = m.keyframeReps.get(m.rungs[rung]!.keyframeRep)!;
      const kfMax = m.maxSegmentBytes(kfRep.bandwidth);
      let keyframe: Promise<DecodedSegment> | null = null;
      const [kf, media] = await Promise.all([
        fetchStream(m.keyframeUrl(k, kfRep.id), m.policy, kfMax, `keyframe segment of GOP ${k}`, signal).then((got) => {
          // decoded in a worker as soon as it is here, while the media segment still streams
          keyframe = this.keyframes.decode({
            data: got.data.slice(0),
            what: "keyframe",
            metadata: keyframeMetadata(k, m.shape, kfRep.quant),
            want: [...keyframeTensors(m.shape, kfRep.quant)],
            side: m.shape.side,
            shDegree: 0,
            maxBytes: kfMax,
            quant: kfRep.quant,
            fieldShapes: quantisedFields(m, kfRep),
          });
          keyframe.catch(() => undefined);
          return got;
        }),
        fetchStream(
          m.mediaUrl(rung, k),
          m.policy,
          m.maxSegmentBytes(m.rungs[rung]!.bandwidth),
          `feature segment of GOP ${k}`,
          signal,
          (chunk) => this.features.chunk(k, chunk, false),
        ),
      ]);
      if (generation !== this.generation) return;
      this.features.chunk(k, null, true);
      const seconds = (performance.now() - start) / 1e3;
      const sample = {
        bytes: kf.sample.bytes + media.sample.bytes,
        seconds,
        ttfb: Math.min(kf.sample.ttfb, media.sample.ttfb),
      };
      this.samples.push(sample);
      // as the cheapest keyframes of the ladder would be (what AbrState.keyframeBits stands for)
      const cheapest = Math.min(...m.rungs.map((r) => r.keyframeBandwidth));
      this.lastKeyframeBits = (kf.sample.bytes * 8 * cheapest) / kfRep.bandwidth;
      this.current = rung;
      this.downloadedUntilS = (k + 1) * T;
      arrived = performance.now();
      this.hooks.onGop({ gop: k, rung, decision, keyframe: keyframe!, bytes: sample.bytes, seconds });
    }
  }
}
