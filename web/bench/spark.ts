// Spark (three.js's Gaussian splat renderer) against our splat pass, on the player's own deformed Gaussians; a
// benchmark page, never part of the player (bench/web/web_spark.py builds and drives it). The player plays frames
// one by one as in bench/web/web.py; Spark then draws the same frame from the same GPU textures: a SplatGenerator
// whose GLSL reads the deform pass's output textures (and the static layer's) by index, so no Gaussian crosses
// to the CPU. Spark regenerates its splat buffer, reads back depths, sorts them in its worker and draws.
// Query: as the player's (mpd, quality, camera, size), plus frames=N, ext=1 (Spark's 32-byte ExtSplats instead
// of its 16-byte PackedSplats), stddev=K (Spark's quad half-size in standard deviations; default 3.33, where
// alpha of the most opaque splat falls below 1/255 as ours does; Spark's own default is 2.83), pictures=1.
import { dyno, SparkRenderer, SplatGenerator } from "@sparkjsdev/spark";
import * as THREE from "three";
import type { View } from "../src/camera";
import { Player, type PlayerOptions } from "../src/player";
import type { FramePipeline } from "../src/render/frame";
import type { Assets } from "../src/stream/worker-pools";

/** The player's GPU side, which the comparison draws from (a private field of the player). */
interface PlayerInternals {
  frames: FramePipeline;
}

interface Result {
  gaussians: number;
  ours: { deform: number; sort: number; draw: number }[];
  spark: { update: number; draw: number }[];
  psnr: number;
  /** The middle frame as PNG data URLs (with pictures=1). */
  pictures: [string, string] | null;
  /** Whether the page's CSP refused a worker from a blob: URL, the way Spark makes its own. */
  blobWorkerRefused: boolean;
  agent: string;
}

declare global {
  interface Window {
    sparkBench?: Promise<Result>;
    sparkWorkerUrl?: string;
  }
}

/** Whether the page's CSP refuses a worker made from a blob: URL, the way Spark makes its own (a refused worker
 * fires "error" instead of running). */
function blobWorkerRefused(): Promise<boolean> {
  const url = URL.createObjectURL(new Blob(["postMessage(1)"], { type: "text/javascript" }));
  return new Promise<boolean>((resolve) => {
    try {
      const worker = new Worker(url);
      worker.onmessage = () => resolve(false);
      worker.onerror = () => resolve(true);
      setTimeout(() => resolve(true), 5000);
    } catch {
      resolve(true);
    }
  }).finally(() => URL.revokeObjectURL(url));
}

/** The generator's GLSL: Gaussian `index` from the static layer's textures, then the dynamic layer's, activated
 * as our splat pass reads them (static colour plus its degree-1 term toward the camera). */
function gaussianProgram(
  staticCount: number,
  staticSide: number,
  shDegree: number,
  dynSide: number,
  inputs: Record<string, string>,
  out: string,
): string[] {
  return [
    `int id = ${inputs.index};`,
    "vec4 mo; vec3 scale; vec4 q; vec3 color;",
    `if (id < ${staticCount}) {`,
    `  ivec2 g = ivec2(id % ${staticSide}, id / ${staticSide});`,
    `  mo = texelFetch(${inputs.sMean}, g, 0); scale = texelFetch(${inputs.sScale}, g, 0).xyz;`,
    `  q = texelFetch(${inputs.sQuat}, g, 0); color = texelFetch(${inputs.sColor}, g, 0).xyz;`,
    ...(shDegree
      ? [
          `  vec3 d = mo.xyz - ${inputs.camera}; d = d / max(length(d), 1e-12);`,
          `  color += d.x * texelFetch(${inputs.sh0}, g, 0).xyz + d.y * texelFetch(${inputs.sh1}, g, 0).xyz`,
          `    + d.z * texelFetch(${inputs.sh2}, g, 0).xyz;`,
        ]
      : []),
    "} else {",
    `  int j = id - ${staticCount};`,
    `  ivec2 g = ivec2(j % ${dynSide}, j / ${dynSide});`,
    `  mo = texelFetch(${inputs.dMean}, g, 0); scale = texelFetch(${inputs.dScale}, g, 0).xyz;`,
    `  q = texelFetch(${inputs.dQuat}, g, 0); color = texelFetch(${inputs.dColor}, g, 0).xyz;`,
    "}",
    "float n = length(q);",
    `${out}.center = mo.xyz;`,
    `${out}.scales = scale;`,
    `${out}.quaternion = n > 0.0 ? vec4(q.y, q.z, q.w, q.x) / n : vec4(0.0, 0.0, 0.0, 1.0);`, // ours wxyz, Spark xyzw
    `${out}.rgba = vec4(max(color, 0.0), mo.w);`,
    `${out}.index = id;`,
    `${out}.flags = 255.0 * mo.w >= 1.0 ? GSPLAT_FLAG_ACTIVE : 0u;`,
  ];
}

function generator(
  internals: PlayerInternals,
  capacity: number,
  dynSide: number,
  camera: dyno.DynoVal<"vec3">,
  external: THREE.ExternalTexture[],
): SplatGenerator {
  const s = internals.frames.staticLayer;
  const staticCount = s ? s.count : 0;
  const sampler = (t: THREE.ExternalTexture) => dyno.dynoSampler2D(t as unknown as THREE.Texture);
  const names = ["dMean", "dScale", "dQuat", "dColor", "sMean", "sScale", "sQuat", "sColor", "sh0", "sh1", "sh2"];
  const program = dyno.dynoBlock({ index: "int" }, { gsplat: dyno.Gsplat }, ({ index }) => {
    const inTypes: Record<string, string> = { index: "int", camera: "vec3" };
    const inputs: Record<string, unknown> = { index, camera };
    external.forEach((t, i) => {
      inTypes[names[i]!] = "sampler2D";
      inputs[names[i]!] = sampler(t);
    });
    type Glsl = { inputs: Record<string, string>; outputs: { gsplat: string } };
    // The inputs are assembled at run time (the static layer's textures only where there is one), which Dyno's
    // generic parameter types cannot follow: hence the casts.
    const d = new dyno.Dyno({
      inTypes,
      outTypes: { gsplat: dyno.Gsplat },
      inputs,
      statements: ({ inputs: glsl, outputs }: Glsl) =>
        gaussianProgram(staticCount, s ? s.side : 1, s ? s.shDegree : 0, dynSide, glsl, outputs.gsplat),
    } as never) as dyno.Dyno<{ index: "int" }, { gsplat: typeof dyno.Gsplat }>;
    return { gsplat: d.outputs.gsplat };
  });
  return new SplatGenerator({ numSplats: staticCount + capacity, generator: program });
}

/** A three.js camera equal to our View: OpenCV pose and pinhole K (skew included) as OpenGL matrices. */

function setCamera(camera: THREE.PerspectiveCamera, view: View): void {
  const flip = new THREE.Matrix4().makeScale(1, -1, -1);
  const worldToCamera = new THREE.Matrix4().set(...(Array.from(view.viewmat) as Parameters<THREE.Matrix4["set"]>));
  camera.matrixAutoUpdate = false;
  camera.matrix.copy(flip.multiply(worldToCamera).invert());
  camera.matrix.decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
  const [fx, skew, cx, fy, cy] = view.K;
  const { width: W, height: H } = view;
  const [near, far] = [0.01, 1000];
  camera.near = near;
  camera.far = far;
  camera.projectionMatrix.set(
    (2 * fx) / W,
    (-2 * skew) / W,
    1 - (2 * cx) / W,
    0,
    0,
    (2 * fy) / H,
    (2 * cy) / H - 1,
    0,
    0,
    0,
    -(far + near) / (far - near),
    (-2 * far * near) / (far - near),
    0,
    0,
    -1,
    0,
  );
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
}

function readCanvas(gl: WebGL2RenderingContext, w: number, h: number): Uint8Array {
  const px = new Uint8Array(4 * w * h);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
  return px;
}

function psnr(a: Uint8Array, b: Uint8Array): number {
  let sum = 0;
  let n = 0;
  for (let i = 0; i < a.length; i++) {
    if (i % 4 === 3) continue;
    sum += (a[i]! - b[i]!) ** 2;
    n++;
  }
  return sum === 0 ? Infinity : 10 * Math.log10((255 * 255) / (sum / n));
}

async function bench(): Promise<Result> {
  const params = new URLSearchParams(location.search);
  const assets = JSON.parse(document.querySelector<HTMLMetaElement>('meta[name="stgs-assets"]')!.content) as Assets & {
    sparkWorker: string;
  };
  window.sparkWorkerUrl = new URL(assets.sparkWorker, location.href).href;
  const [w = 640, h = 360] = (params.get("size") ?? "640x360").split("x").map(Number);
  const frames = Number(params.get("frames") ?? 12);
  const options: PlayerOptions = {
    abr: "dynamic",
    rung: null,
    bufferGops: 3,
    background: [0, 0, 0],
    size: [w, h],
    syncTiming: true,
    digests: false,
    weights: null,
    webgpu: false,
    loop: false,
  };
  const canvas = document.getElementById("view") as HTMLCanvasElement;
  const player = new Player(canvas, assets, options);
  player.paused = true;
  await player.load(params.get("mpd")!);
  const rung = player.manifest.rungs.findIndex((r) => r.id === params.get("quality"));
  if (rung >= 0) {
    player.options.rung = rung;
    player.setRung(rung);
  }
  player.snapTo(
    Math.max(
      0,
      player.cameras.findIndex((c) => c.name === params.get("camera")),
    ),
  );
  const internals = player as unknown as PlayerInternals;
  const gl = canvas.getContext("webgl2")!;

  // Ours first, alone: the stage times and the reference picture of the middle frame.
  const middle = Math.floor(frames / 2);
  let oursPicture: Uint8Array = new Uint8Array(0);
  let oursPng = "";
  for (let f = 0; f < frames; f++) {
    await player.showFrame(f);
    if (f === middle) [oursPicture, oursPng] = [readCanvas(gl, w, h), canvas.toDataURL()];
  }
  const ours = player.stats.frameTimes
    .slice(-frames)
    .map((t) => ({ deform: t.deform, sort: t.sortWait, draw: t.draw }));

  const renderer = new THREE.WebGLRenderer({ canvas, context: gl, antialias: false });
  renderer.setPixelRatio(1);
  renderer.setSize(w, h, false);
  renderer.outputColorSpace = THREE.SRGBColorSpace; // Spark writes the colours as they are (no sRGB-to-linear)
  renderer.setClearColor(0x000000, 1);
  const scene = new THREE.Scene();
  const spark = new SparkRenderer({
    renderer,
    autoUpdate: false,
    minSortIntervalMs: 0,
    minAlpha: 1 / 255,
    blurAmount: 0.3,
    preBlurAmount: 0,
    maxStdDev: Number(params.get("stddev") ?? Math.sqrt(2 * Math.log(255))),
    sortRadial: false,
    accumExtSplats: params.get("ext") === "1",
    enableLod: false,
  });
  scene.add(spark);
  const camera = new THREE.PerspectiveCamera();
  const eye = dyno.dynoVec3(new THREE.Vector3());
  const sources = () => [...internals.frames.deformer.outputs, ...(internals.frames.staticLayer?.textures ?? [])];
  const external = sources().map((t) => new THREE.ExternalTexture(t));
  const splats = generator(internals, player.manifest.shape.capacity, player.manifest.shape.side, eye, external);
  scene.add(splats);
  const spk: Result["spark"] = [];
  let sparkPicture: Uint8Array = new Uint8Array(0);
  let sparkPng = "";
  for (let f = 0; f < frames; f++) {
    renderer.resetState();
    await player.showFrame(f);
    renderer.resetState();
    const view = player.camera.view(w, h);
    setCamera(camera, view);
    eye.value.copy(camera.position);
    sources().forEach((t, i) => {
      external[i]!.sourceTexture = t;
    });
    const t0 = performance.now();
    splats.updateVersion();
    await spark.update({ scene, camera });
    const t1 = performance.now();
    renderer.render(scene, camera);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
    spk.push({ update: t1 - t0, draw: performance.now() - t1 });
    if (f === middle) [sparkPicture, sparkPng] = [readCanvas(gl, w, h), canvas.toDataURL()];
  }
  renderer.resetState();
  return {
    gaussians: splats.numSplats,
    ours,
    spark: spk,
    psnr: psnr(oursPicture, sparkPicture),
    pictures: params.get("pictures") === "1" ? [oursPng, sparkPng] : null,
    blobWorkerRefused: await blobWorkerRefused(),
    agent: navigator.userAgent,
  };
}

window.sparkBench = bench();
