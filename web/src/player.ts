// The player: loads a manifest and what sits beside it, streams GOPs through the downloader and the decoders,
// and presents frames on the wall clock: the frame the clock asks for is shown if its keyframe and feature
// window are here, frames it passed are dropped, and only when nothing new is ready does the clock stop (a
// stall). Each shown frame: deform the dynamic layer (GPU), read back its means, depth-sort both layers
// (worker), splat (GPU). At the end it stops, or starts again from the first frame when it loops. A still scene (the
// static layer alone) has no clock: it is drawn once, and again whenever the camera moves.
import { DEFAULT_SETTINGS, type Decision, makeRule } from "./abr/index";
import { type SceneCamera, ViewerCamera, cameraCenter, parseSceneCameras, sceneCenter, sceneUp } from "./camera";
import { PresentationClock, SPEEDS } from "./clock";
import { UnsupportedError, describe } from "./errors";
import * as L from "./limits";
import { type Manifest, parseManifest } from "./manifest";
import { UrlPolicy } from "./urlpolicy";
import { type SceneFace, parseSceneFace } from "./scene";
import { DeformPass, type WeightStorage } from "./render/deform";
import { WebGpuDeform } from "./render/deform-webgpu";
import type { Deformer } from "./render/deformer";
import { createContext } from "./render/gl";
import { FramePipeline, StillFrame } from "./render/frame";
import { SplatPass, type StaticTextures, staticTextures } from "./render/splat";
import { Downloader, type GopDownload, type GopState } from "./stream/downloader";
import { fetchJson, fetchStream } from "./stream/fetch";
import { loadStaticLayer } from "./stream/static-layer";
import { FeatureRing } from "./stream/ring";
import { type Assets, FeatureDecoder, KeyframePool, Sorter } from "./stream/worker-pools";
import { PlayerStats, sha256Hex } from "./stats";

export interface PlayerOptions {
  abr: string;
  /** Pinned rung index, or null for adaptive. */
  rung: number | null;
  bufferGops: number;
  background: [number, number, number];
  /** Fixed render size (else the canvas' CSS size x devicePixelRatio). */
  size: [number, number] | null;
  /** After each draw, wait for the GPU (exact per-stage times, for benchmarks). */
  syncTiming: boolean;
  /** Keep a SHA-256 of every decoded feature frame (tests). */
  digests: boolean;
  /** Where the deformation weights live (null: a texture). */
  weights: WeightStorage | null;
  /** Run the deformation as a WebGPU compute shader (where navigator.gpu exists) instead of WebGL2. */
  webgpu: boolean;
  /** Start again at the end (null: loop scenes shorter than LOOP_UNDER_S). */
  loop: boolean | null;
}

/** Scenes shorter than this (seconds) loop unless told otherwise. */
export const LOOP_UNDER_S = 10;

export class Player {
  manifest!: Manifest;
  cameras: SceneCamera[] = [];
  readonly camera = new ViewerCamera();
  readonly stats = new PlayerStats();
  readonly digests = new Map<string, string>();
  private downloader!: Downloader;
  private ring!: FeatureRing;
  private features!: FeatureDecoder;
  private keyframes!: KeyframePool;
  private sorter!: Sorter;
  private deform!: Deformer;
  private frames!: FramePipeline;
  /** A still scene's frame (null for a scene of GOPs). */
  private stillFrame: StillFrame | null = null;
  private readonly gops = new Map<number, GopState>();
  /** Last presented frame (global index), -1 before the first. */
  current = -1;
  private clock!: PresentationClock;
  paused = false;
  ended = false;
  /** Start again from the first frame at the end. */
  loop = false;
  /** How many times playback reached the end and started again. */
  loops = 0;
  /** scene.json's title, description and poster (null: the tree has none, or it did not hold up). */
  scene: SceneFace | null = null;
  private started = false;
  private busy = false;
  private dirty = false;
  /** `current` was presented since the last seek (so it can be drawn again when the camera moves). */
  private presentable = false;
  onError: (message: string) => void = () => undefined;
  onDecision: (d: Decision, gop: number, rung: number) => void = () => undefined;
  /** The scene's face is known (called once during load, before the first GOP arrives). */
  onScene: (face: SceneFace | null) => void = () => undefined;

  constructor(
    private readonly canvas: HTMLCanvasElement,
    private readonly assets: Assets,
    readonly options: PlayerOptions,
  ) {}

  get totalFrames(): number {
    return this.still ? 1 : this.manifest.gops * this.manifest.shape.gopSize;
  }

  /** A still scene: no clock, no GOP, nothing to play. */
  get still(): boolean {
    return this.manifest.still;
  }

  playheadS(): number {
    return Math.max(0, this.current + 1) / this.manifest.fps;
  }

  async load(url: string): Promise<void> {
    const start = performance.now();
    const ctx = createContext(this.canvas);
    const absolute = new URL(url, document.baseURI).href;
    const text = await fetchStream(absolute, new UrlPolicy(absolute), L.MAX_MPD_BYTES, "manifest", null);
    this.manifest = parseManifest(new TextDecoder().decode(text.data), absolute);
    const m = this.manifest;
    if (!m.still && typeof VideoDecoder === "undefined")
      throw new UnsupportedError("this browser has no WebCodecs VideoDecoder, which the feature video (AV1) needs");
    this.clock = new PresentationClock(m.fps);
    this.loop = this.options.loop ?? m.durationS < LOOP_UNDER_S;
    // a scene may come without stats, cameras or a face (an older tree): each is optional
    const [stats, cameras, scene] = await Promise.all([
      fetchJson(m.statsUrl, m.policy, L.MAX_DOC_BYTES, "stats.json").catch(() => null),
      fetchJson(m.camerasUrl, m.policy, L.MAX_DOC_BYTES, "cameras.json")
        .then((doc) => parseSceneCameras(doc, L.MAX_PATH_CAMERAS))
        .catch(() => []),
      fetchJson(m.sceneUrl, m.policy, L.MAX_DOC_BYTES, "scene.json")
        .then((doc) => parseSceneFace(doc, m.sceneUrl))
        .catch(() => null),
    ]);
    this.cameras = cameras;
    this.scene = scene;
    this.onScene(scene);
    this.camera.up = sceneUp(this.cameras);
    this.camera.target = sceneCenter(this.cameras);
    if (this.cameras.length) this.snapTo(0);
    this.keyframes = new KeyframePool(this.assets, Math.max(1, Math.min(4, (navigator.hardwareConcurrency || 2) - 1)));
    this.sorter = new Sorter(this.assets);
    if (m.still) return this.loadStill(ctx.gl, ctx.floatBlend, start);
    this.features = new FeatureDecoder(this.assets);
    this.features.onFrame = (f) => {
      if (this.options.digests) void sha256Hex(f.data).then((hex) => this.digests.set(`${f.gop}:${f.index}`, hex));
      this.ring.add(f);
    };
    this.features.onError = (_gop, err) => this.fail(err);
    this.ring = new FeatureRing(this.features, Math.max(8, 2 * m.shape.window + 2));
    const slots = this.ring.capacity + m.shape.window;
    this.deform = this.options.webgpu
      ? await WebGpuDeform.create(ctx.gl, m.shape, slots)
      : new DeformPass(ctx.gl, m.shape, slots, this.options.weights ?? undefined);
    this.stats.deformer = this.deform.kind;
    this.stats.floatBlend = ctx.floatBlend;
    let staticLayer: StaticTextures | null = null;
    if (m.staticLayer) {
      const layer = await loadStaticLayer(m, this.keyframes, this.sorter);
      staticLayer = staticTextures(ctx.gl, layer.attributes, layer.capacity, layer.side, layer.shDegree);
      this.stats.staticMs = layer.ms;
    }
    const sorter = this.sorter;
    this.frames = new FramePipeline(
      this.deform,
      new SplatPass(ctx.gl, ctx.floatBlend),
      (means, viewmat, guard) => sorter.sort(means, viewmat, guard),
      staticLayer,
      m.shape.side,
      this.options.background,
      this.options.syncTiming,
    );
    const settings = DEFAULT_SETTINGS;
    this.downloader = new Downloader(
      m,
      makeRule(this.options.abr, settings),
      settings,
      this.features,
      this.keyframes,
      this.options.bufferGops * m.gopSeconds,
      stats,
      {
        playheadS: () => this.playheadS(),
        playing: () => this.started,
        onGop: (d) => this.onGop(d),
        onError: (e) => this.fail(e),
      },
    );
    this.downloader.pinned = this.options.rung;
    this.stats.loadMs = performance.now() - start;
    this.seek(0);
    requestAnimationFrame((t) => this.tick(t));
  }

  /** A still scene: its static layer fetched, decoded and drawn (then redrawn whenever the view changes). */
  private async loadStill(gl: WebGL2RenderingContext, floatBlend: boolean, start: number): Promise<void> {
    const m = this.manifest;
    const layer = await loadStaticLayer(m, this.keyframes, this.sorter);
    this.stats.staticMs = layer.ms;
    const textures = staticTextures(gl, layer.attributes, layer.capacity, layer.side, layer.shDegree);
    const sorter = this.sorter;
    this.stillFrame = new StillFrame(
      new SplatPass(gl, floatBlend),
      (means, viewmat, guard) => sorter.sort(means, viewmat, guard),
      textures,
      this.options.background,
      this.options.syncTiming,
    );
    this.loop = false;
    this.stats.loadMs = performance.now() - start;
    this.stats.seekStart = start; // a still's start-up runs from the manifest's request to its one picture
    this.dirty = true;
    requestAnimationFrame((t) => this.tick(t));
  }

  private fail(err: unknown): void {
    this.paused = true;
    this.downloader?.stop();
    this.onError(describe(err));
  }

  private onGop(d: GopDownload): void {
    const state: GopState = { download: d, decoded: null };
    this.gops.set(d.gop, state);
    this.stats.onGop(d, this.manifest.rungs[d.rung]!.id);
    this.onDecision(d.decision, d.gop, d.rung);
    d.keyframe.then(
      (k) => {
        state.decoded = k;
        this.stats.keyframeMs = k.ms;
      },
      (e) => this.fail(e),
    );
  }

  snapTo(index: number): void {
    const cam = this.cameras[index];
    if (!cam) return;
    const center = sceneCenter(this.cameras);
    const v = cam.viewmat;
    const c = cameraCenter(v.flat());
    const dist = Math.max(0.1, Math.hypot(center[0] - c[0], center[1] - c[1], center[2] - c[2]));
    this.camera.snap(cam, dist);
    this.dirty = true;
  }

  invalidate(): void {
    this.dirty = true;
  }

  setRung(rung: number | null): void {
    if (!this.still) this.downloader.pinned = rung;
  }

  /** Jump to GOP k: drop what is buffered and fetch from k on (only what k needs: its keyframe and features). */
  seek(k: number): void {
    if (this.still) return;
    const gop = Math.max(0, Math.min(this.manifest.gops - 1, k));
    this.downloader.stop();
    this.features.reset();
    this.gops.clear();
    this.frames.forget();
    this.current = gop * this.manifest.shape.gopSize - 1;
    this.clock.restart(this.current + 1);
    this.started = false;
    this.ended = false;
    this.presentable = false;
    this.stats.seekStart = performance.now();
    this.ring.start(gop);
    this.downloader.start(gop);
  }

  /** Jump to the frame at scene time `t` (seconds, clamped to the scene): its GOP is fetched and the clock starts
   * at that frame. */
  seekTime(t: number): void {
    if (this.still) return;
    const G = this.manifest.shape.gopSize;
    const frame = Math.max(0, Math.min(this.totalFrames - 1, Math.round(t * this.manifest.fps)));
    const k = Math.floor(frame / G);
    this.seek(k);
    this.current = frame - 1;
    this.clock.restart(frame);
    this.ring.release(k, frame % G);
  }

  /** The scene time (seconds) of the frame on screen. */
  shownTimeS(): number {
    return this.still ? 0 : Math.max(0, this.current) / this.manifest.fps;
  }

  get speed(): number {
    return this.clock.speed;
  }

  /** Playback speed, one of SPEEDS (scene seconds per second); the clock goes on from the frame on screen. */
  setSpeed(speed: number): void {
    if (!(SPEEDS as readonly number[]).includes(speed)) throw new RangeError(`speed ${speed} is not one of ${SPEEDS}`);
    if (this.still) return;
    this.clock.speed = speed;
    this.clock.restart(this.current + 1);
  }

  togglePause(): void {
    if (this.still) return;
    this.paused = !this.paused;
    if (!this.paused) {
      if (this.ended) this.seek(0);
      this.clock.restart(this.current + 1);
    }
  }

  /** Pause and show presentation frame `frame` (seeking to its GOP unless it is ahead in the current one) once
   * its data is here: what the tests and the benchmark use to look at one exact frame. */
  async showFrame(frame: number, timeoutMs = 60000): Promise<{ gop: number; frame: number }> {
    if (this.still) {
      if (frame !== 0) throw new RangeError(`a still scene has one frame, not frame ${frame}`);
      await this.whenIdle(timeoutMs);
      await this.presentStill();
      return { gop: 0, frame: 0 };
    }
    const G = this.manifest.shape.gopSize;
    const k = Math.floor(frame / G);
    this.paused = true;
    if (frame < this.current || Math.floor(Math.max(0, this.current + 1) / G) !== k) this.seek(k);
    this.ring.release(k, frame % G);
    const until = performance.now() + timeoutMs;
    while (!this.ready(frame) || this.busy) {
      if (performance.now() > until) throw new Error(`frame ${frame} did not arrive within ${timeoutMs} ms`);
      await new Promise((r) => setTimeout(r, 20));
    }
    this.busy = true;
    try {
      await this.present(frame, performance.now());
    } finally {
      this.busy = false;
    }
    return { gop: k, frame: frame % G };
  }

  /** The canvas as a PNG data URL (the last presented frame). */
  capture(): string {
    return this.canvas.toDataURL("image/png");
  }

  private ready(frame: number): boolean {
    const G = this.manifest.shape.gopSize;
    const k = Math.floor(frame / G);
    return this.gops.get(k)?.decoded != null && this.ring.has(k, frame % G, this.manifest.shape.window);
  }

  /** Wait until no frame is being drawn. */
  private async whenIdle(timeoutMs: number): Promise<void> {
    const until = performance.now() + timeoutMs;
    while (this.busy) {
      if (performance.now() > until) throw new Error(`the frame being drawn did not finish within ${timeoutMs} ms`);
      await new Promise((r) => setTimeout(r, 20));
    }
  }

  /** Draw a still scene from the current view. */
  private async presentStill(): Promise<void> {
    this.busy = true;
    try {
      const [w, h] = this.renderSize();
      if (this.canvas.width !== w || this.canvas.height !== h) [this.canvas.width, this.canvas.height] = [w, h];
      this.dirty = false;
      const t = await this.stillFrame!.draw(this.camera.view(w, h));
      if (!this.started) {
        this.started = true;
        this.stats.started(performance.now()); // the first picture is on screen now, not at the frame's start
      }
      this.current = 0;
      this.presentable = true;
      this.stats.frame(t.deform, t.sort, t.sortWait, t.draw, 0, t.visible);
      this.stats.shown = { gop: 0, frame: 0 };
    } finally {
      this.busy = false;
    }
  }

  private async tick(now: number): Promise<void> {
    requestAnimationFrame((t) => this.tick(t));
    if (this.busy || !this.manifest) return;
    if (this.still) {
      if (this.dirty) await this.presentStill().catch((err) => this.fail(err));
      return;
    }
    if (this.ended && this.loop && !this.paused) {
      this.loops++;
      this.seek(0);
    }
    let next = -1;
    if (!this.paused && !this.ended) {
      const due = this.clock.next(now, this.current, this.totalFrames, (f) => this.ready(f));
      next = due.frame;
      if (due.stalled) this.stats.stalled(now);
    }
    if (this.paused && !this.presentable && this.clock.frame < this.totalFrames && this.ready(this.clock.frame)) {
      next = this.clock.frame; // a seek while paused shows the new GOP's first frame
    }
    if (next < 0 && !(this.dirty && this.presentable)) return;
    const frame = next >= 0 ? next : this.current;
    this.busy = true;
    try {
      await this.present(frame, now);
    } catch (err) {
      this.fail(err);
    } finally {
      this.busy = false;
    }
  }

  private async present(frame: number, now: number): Promise<void> {
    const G = this.manifest.shape.gopSize;
    const W = this.manifest.shape.window;
    const k = Math.floor(frame / G);
    const i = frame % G;
    if (frame !== this.current) {
      this.stats.presented(now, frame - this.current - 1, this.started);
      if (!this.started) {
        this.started = true;
        this.stats.started(now);
      }
      this.current = frame;
      if (frame === this.totalFrames - 1) this.ended = true;
    }
    this.dirty = false;
    this.presentable = true;
    const state = this.gops.get(k)!;
    if (!this.frames.holds(k)) for (const old of this.gops.keys()) if (old < k) this.gops.delete(old);
    const [w, h] = this.renderSize();
    if (this.canvas.width !== w || this.canvas.height !== h) [this.canvas.width, this.canvas.height] = [w, h];
    const view = this.camera.view(w, h);
    const t = await this.frames.draw(k, i, W, state.decoded!, (e) => this.ring.get(k, e)!, view);
    this.ring.release(k, i);
    this.stats.frame(t.deform, t.sort, t.sortWait, t.draw, this.ring.copyMs, t.visible);
    this.stats.shown = { gop: k, frame: i };
  }

  renderSize(): [number, number] {
    if (this.options.size) return this.options.size;
    const dpr = Math.min(2, window.devicePixelRatio || 1);
    return [
      Math.max(1, Math.round(this.canvas.clientWidth * dpr)),
      Math.max(1, Math.round(this.canvas.clientHeight * dpr)),
    ];
  }

  bufferS(): number {
    if (this.still) return 0;
    return Math.max(0, this.downloader.downloadedUntilS - this.playheadS());
  }
}
