// What the stats overlay shows and the tests and benchmarks read: the rung, throughput, buffer, fps, per-stage
// times (decode, deform, sort, draw), dropped frames, stalls and the last ABR decision's reason.
import type { GopDownload } from "./stream/downloader";

const SMOOTH = 0.9;

export class PlayerStats {
  rung = "";
  kbps = 0;
  reason = "";
  rule = "";
  presentedFrames = 0;
  dropped = 0;
  stalls = 0;
  stallMs = 0;
  fps = 0;
  deformMs = 0;
  sortMs = 0;
  sortWaitMs = 0;
  drawMs = 0;
  copyMs = 0;
  keyframeMs = 0;
  staticMs = 0;
  loadMs = 0;
  startupMs = 0;
  seekMs = 0;
  seekStart = 0;
  visible = 0;
  floatBlend = true;
  deformer = "";
  shown: { gop: number; frame: number } | null = null;
  readonly decisions: { gop: number; rung: string; rule: string; reason: string }[] = [];
  readonly frameTimes: { deform: number; sort: number; sortWait: number; draw: number }[] = [];
  private stallStart = -1;
  private lastFrameAt = -1;
  private firstStart = -1;

  onGop(d: GopDownload, rung: string): void {
    this.rung = rung;
    this.kbps = (d.bytes * 8) / 1e3 / Math.max(d.seconds, 1e-6);
    this.reason = d.decision.reason;
    this.rule = d.decision.rule;
    this.decisions.push({ gop: d.gop, rung, rule: d.decision.rule, reason: d.decision.reason });
  }

  stalled(now: number): void {
    if (this.stallStart < 0) {
      this.stallStart = now;
      this.stalls++;
    }
  }

  started(now: number): void {
    if (this.firstStart < 0) {
      this.firstStart = now;
      this.startupMs = now - this.seekStart;
    }
    this.seekMs = now - this.seekStart;
  }

  presented(now: number, dropped: number, playing: boolean): void {
    if (this.stallStart >= 0) {
      this.stallMs += now - this.stallStart;
      this.stallStart = -1;
    }
    if (playing) this.dropped += Math.max(0, dropped);
    this.presentedFrames++;
    if (this.lastFrameAt >= 0) {
      const inst = 1000 / Math.max(now - this.lastFrameAt, 1e-3);
      this.fps = this.fps ? SMOOTH * this.fps + (1 - SMOOTH) * inst : inst;
    }
    this.lastFrameAt = now;
  }

  frame(deform: number, sort: number, sortWait: number, draw: number, copy: number, visible: number): void {
    const s = (a: number, b: number) => (a ? SMOOTH * a + (1 - SMOOTH) * b : b);
    this.deformMs = s(this.deformMs, deform);
    this.sortMs = s(this.sortMs, sort);
    this.sortWaitMs = s(this.sortWaitMs, sortWait);
    this.drawMs = s(this.drawMs, draw);
    this.copyMs = copy;
    this.visible = visible;
    if (this.frameTimes.length < 10000) this.frameTimes.push({ deform, sort, sortWait, draw });
  }

  lines(bufferS: number): string[] {
    return [
      `rung ${this.rung || "-"}  ${this.kbps.toFixed(0)} kbit/s  buffer ${bufferS.toFixed(2)} s`,
      `${this.fps.toFixed(1)} fps  ${this.visible} splats  dropped ${this.dropped}  stalls ${this.stalls} (${(this.stallMs / 1e3).toFixed(2)} s)`,
      `decode: keyframe ${this.keyframeMs.toFixed(1)} ms, feature copy ${this.copyMs.toFixed(2)} ms`,
      `${this.deformer}: deform ${this.deformMs.toFixed(1)}  sort ${this.sortMs.toFixed(1)}  draw ${this.drawMs.toFixed(1)} ms${this.floatBlend ? "" : "  (16-bit blending)"}`,
      `ABR ${this.rule}: ${this.reason}`,
    ];
  }
}

/** SHA-256 of `data` as hex (the tests compare decoded feature frames with the Python decoder's). */
export async function sha256Hex(data: Uint16Array<ArrayBuffer>): Promise<string> {
  const digest = await crypto.subtle.digest("SHA-256", data);
  return Array.from(new Uint8Array(digest), (b) => b.toString(16).padStart(2, "0")).join("");
}
