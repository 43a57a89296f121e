// The deformation field as a WebGPU compute shader (where navigator.gpu exists): one invocation per Gaussian of
// the dynamic layer, the same arithmetic as the WebGL2 fragment shader (render/deform.ts). WebGPU and WebGL
// share no resources, so the result is read back (the sort needs the means on the CPU anyway) and uploaded to
// the four textures the WebGL2 splat pass reads: one more copy than the WebGL2 path (docs/WEB.md measures it).
import { type Attributes, fieldShapes } from "../container";
import { UnsupportedError } from "../errors";
import type { SceneShape } from "../manifest";
import { floatTexture, rgba } from "./gl";
import { CODE_MAX, type Deformer, LayerRing, dequantisation, packWeights, positionalEncoding } from "./deformer";

function wgsl(shape: SceneShape, offsets: Record<string, [number, number]>): string {
  const W = shape.window;
  const peVec = Math.max(1, Math.ceil((2 * shape.peFreqs) / 4));
  const inVec = W * 4 + Math.ceil((2 * shape.peFreqs) / 4);
  const o = (n: string) => offsets[n]![0];
  const dense64 = (name: string, input: string, extra: boolean) => `
  for (var j = 0u; j < 64u; j++) {
    let row = ${o(name)}u + j * ${extra ? 17 : 16}u;
    var acc = 0.0;
    for (var i = 0u; i < 16u; i++) { acc += dot(wts[row + i], ${input}[i]); }
    ${extra ? "acc += dot(wts[row + 16u], vv);" : ""}
    a[j / 4u][j % 4u] = max(acc, 0.0);
  }`;
  const head = (name: string, out: string, count: number) => `
  for (var r = 0u; r < ${count}u; r++) {
    var acc = 0.0;
    for (var i = 0u; i < 16u; i++) { acc += dot(wts[${o(name)}u + r * 16u + i], a[i]); }
    ${out}[r] = acc;
  }`;
  return `
struct Params {
  lo: array<vec4f, 4>,
  step: array<vec4f, 4>,
  pe: array<vec4f, ${peVec}>,
  cam: vec4f,
  side: u32,
  frameWords: u32,
  pad0: u32,
  pad1: u32,
  layers: array<vec4u, ${Math.ceil(W / 4)}>,
};
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> canon: array<vec4f>;
@group(0) @binding(2) var<storage, read> wts: array<vec4f>;
@group(0) @binding(3) var<storage, read> feats: array<u32>;
@group(0) @binding(4) var<storage, read_write> outp: array<vec4f>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3u) {
  let n = P.side * P.side;
  let g = id.x;
  if (g >= n) { return; }
  let gx = g % P.side;
  let gy = g / P.side;
  var x: array<vec4f, ${inVec}>;
  for (var s = 0u; s < ${W}u; s++) {
    let base = P.layers[s / 4u][s % 4u] * P.frameWords;
    for (var c = 0u; c < 16u; c++) {
      let idx = ((c / 4u) * P.side + gy) * 4u * P.side + (c % 4u) * P.side + gx;
      let code = (feats[base + idx / 2u] >> (16u * (idx % 2u))) & 0xffffu;
      x[4u * s + c / 4u][c % 4u] = f32(code) * P.step[c / 4u][c % 4u] + P.lo[c / 4u][c % 4u];
    }
  }
  for (var k = 0u; k < ${inVec - 4 * W}u; k++) { x[${4 * W}u + k] = P.pe[k]; }
  var h: array<vec4f, 16>;
  for (var j = 0u; j < 64u; j++) {
    let row = ${o("temporal.weight")}u + j * ${inVec}u;
    var acc = 0.0;
    for (var i = 0u; i < ${inVec}u; i++) { acc += dot(wts[row + i], x[i]); }
    h[j / 4u][j % 4u] = tanh(acc);
  }
  var a: array<vec4f, 16>;
  var dpos: array<f32, 3>;
  var dcov: array<f32, 7>;
  var dop: array<f32, 1>;
  var dcol: array<f32, 3>;
  ${dense64("d_pos.0.weight", "h", false)}
  ${head("d_pos.2.weight", "dpos", 3)}
  ${dense64("d_cov.0.weight", "h", false)}
  ${head("d_cov.2.weight", "dcov", 7)}
  let X = canon[4u * g];
  let mean = X.xyz + vec3f(dpos[0], dpos[1], dpos[2]);
  let view = mean - P.cam.xyz;
  let vv = vec4f(view / max(length(view), 1e-12), 0.0);
  ${dense64("d_opacity.0.weight", "h", true)}
  ${head("d_opacity.2.weight", "dop", 1)}
  ${dense64("d_color.0.weight", "h", true)}
  ${head("d_color.2.weight", "dcol", 3)}
  let opacity = clamp(1.0 / (1.0 + exp(-X.w)) + tanh(dop[0]), 0.0, 1.0);
  outp[g] = vec4f(mean, opacity);
  outp[n + g] = vec4f(exp(canon[4u * g + 1u].xyz + vec3f(dcov[0], dcov[1], dcov[2])), 0.0);
  outp[2u * n + g] = canon[4u * g + 2u] + vec4f(dcov[3], dcov[4], dcov[5], dcov[6]);
  outp[3u * n + g] = vec4f(max(canon[4u * g + 3u].xyz, vec3f(0.0)) + vec3f(dcol[0], dcol[1], dcol[2]), 0.0);
}`;
}

export class WebGpuDeform implements Deformer {
  readonly kind = "webgpu compute";
  readonly outputs: WebGLTexture[];
  private readonly ring: LayerRing;
  private readonly pipeline: GPUComputePipeline;
  private readonly params: GPUBuffer;
  private readonly canon: GPUBuffer;
  private readonly weights: GPUBuffer;
  private readonly feats: GPUBuffer;
  private readonly out: GPUBuffer;
  private readonly read: GPUBuffer;
  private readonly bind: GPUBindGroup;
  private lo: Float32Array = new Float32Array(16);
  private step: Float32Array = new Float32Array(16);
  private readonly n: number;

  static async create(gl: WebGL2RenderingContext, shape: SceneShape, slots: number): Promise<WebGpuDeform> {
    const adapter = await navigator.gpu?.requestAdapter();
    if (!adapter) throw new UnsupportedError("this browser has no WebGPU adapter");
    const n = shape.capacity;
    const frameBytes = 16 * n * 2;
    const needed = Math.max(frameBytes * slots, 16 * 4 * n);
    if (needed > adapter.limits.maxStorageBufferBindingSize)
      throw new UnsupportedError("the scene is too large for this GPU's storage buffers");
    const device = await adapter.requestDevice({
      requiredLimits: { maxStorageBufferBindingSize: needed, maxBufferSize: needed },
    });
    return new WebGpuDeform(gl, device, shape, slots);
  }

  private constructor(
    private readonly gl: WebGL2RenderingContext,
    private readonly device: GPUDevice,
    private readonly shape: SceneShape,
    slots: number,
  ) {
    const n = shape.capacity;
    this.n = n;
    const shapes = fieldShapes(shape.window, shape.peFreqs);
    const zeros = Object.fromEntries(
      Object.entries(shapes).map(([k, [r, c]]) => [`field.${k}`, new Float32Array(r * c)]),
    );
    const layout = packWeights(zeros, shape.window, shape.peFreqs);
    const module = device.createShaderModule({ code: wgsl(shape, layout.offsets) });
    this.pipeline = device.createComputePipeline({ layout: "auto", compute: { module, entryPoint: "main" } });
    const S = GPUBufferUsage;
    const peVec = Math.max(1, Math.ceil((2 * shape.peFreqs) / 4));
    this.params = device.createBuffer({
      size: 16 * (4 + 4 + peVec + 1 + 1 + Math.ceil(shape.window / 4)),
      usage: S.UNIFORM | S.COPY_DST,
    });
    this.canon = device.createBuffer({ size: 64 * n, usage: S.STORAGE | S.COPY_DST });
    this.weights = device.createBuffer({ size: layout.texels.byteLength, usage: S.STORAGE | S.COPY_DST });
    const frameWords = 8 * n; // (4S)² codes of 16 bits
    this.feats = device.createBuffer({ size: 4 * frameWords * slots, usage: S.STORAGE | S.COPY_DST });
    this.out = device.createBuffer({ size: 64 * n, usage: S.STORAGE | S.COPY_SRC });
    this.read = device.createBuffer({ size: 64 * n, usage: S.MAP_READ | S.COPY_DST });
    this.bind = device.createBindGroup({
      layout: this.pipeline.getBindGroupLayout(0),
      entries: [this.params, this.canon, this.weights, this.feats, this.out].map((buffer, binding) => ({
        binding,
        resource: { buffer },
      })),
    });
    this.ring = new LayerRing(slots, (slot, codes) =>
      device.queue.writeBuffer(this.feats, 4 * frameWords * slot, codes as Uint16Array<ArrayBuffer>),
    );
    this.outputs = [0, 1, 2, 3].map(() => floatTexture(gl, shape.side, shape.side, null));
  }

  loadGop(attributes: Attributes, floats: Record<string, Float32Array>): void {
    const n = this.n;
    const canon = new Float32Array(16 * n);
    const parts = [
      rgba(attributes.position, 3, n),
      rgba(attributes.scale, 3, n),
      rgba(attributes.rotation, 4, n),
      rgba(attributes.color, 3, n),
    ];
    for (let i = 0; i < n; i++) {
      parts[0]![4 * i + 3] = attributes.opacity[i]!;
      for (let p = 0; p < 4; p++) canon.set(parts[p]!.subarray(4 * i, 4 * i + 4), 16 * i + 4 * p);
    }
    this.device.queue.writeBuffer(this.canon, 0, canon);
    this.device.queue.writeBuffer(
      this.weights,
      0,
      packWeights(floats, this.shape.window, this.shape.peFreqs).texels as Float32Array<ArrayBuffer>,
    );
    [this.lo, this.step] = dequantisation(floats["range.features"]!, CODE_MAX);
  }

  layer(gop: number, e: number, codes: () => Uint16Array): number {
    return this.ring.slot(gop, e, codes);
  }

  forget(): void {
    this.ring.forget();
  }

  async deform(frame: number, layers: number[], camera: ArrayLike<number>): Promise<Float32Array> {
    const { shape, device, n } = this;
    const pe = positionalEncoding(frame, shape.gopSize, shape.peFreqs);
    const peVec = Math.max(1, Math.ceil((2 * shape.peFreqs) / 4));
    const params = new ArrayBuffer(this.params.size);
    const f = new Float32Array(params);
    const u = new Uint32Array(params);
    f.set(this.lo, 0);
    f.set(this.step, 16);
    f.set(pe.subarray(0, 4 * peVec), 32);
    const at = 32 + 4 * peVec;
    f.set([camera[0]!, camera[1]!, camera[2]!, 0], at);
    u.set([shape.side, 8 * n, 0, 0], at + 4);
    u.set(layers, at + 8);
    device.queue.writeBuffer(this.params, 0, params);
    const encoder = device.createCommandEncoder();
    const pass = encoder.beginComputePass();
    pass.setPipeline(this.pipeline);
    pass.setBindGroup(0, this.bind);
    pass.dispatchWorkgroups(Math.ceil(n / 64));
    pass.end();
    encoder.copyBufferToBuffer(this.out, 0, this.read, 0, 64 * n);
    device.queue.submit([encoder.finish()]);
    await this.read.mapAsync(GPUMapMode.READ);
    const all = new Float32Array(this.read.getMappedRange().slice(0));
    this.read.unmap();
    const gl = this.gl;
    this.outputs.forEach((tex, k) => {
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texSubImage2D(
        gl.TEXTURE_2D,
        0,
        0,
        0,
        shape.side,
        shape.side,
        gl.RGBA,
        gl.FLOAT,
        all.subarray(4 * n * k, 4 * n * (k + 1)),
      );
    });
    return all.slice(0, 4 * n);
  }

  sync(): void {
    const px = new Uint8Array(4);
    this.gl.readPixels(0, 0, 1, 1, this.gl.RGBA, this.gl.UNSIGNED_BYTE, px);
  }
}
