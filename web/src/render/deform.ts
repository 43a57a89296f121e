// The deformation field on the GPU (stgs/model/gop.py): one fragment per Gaussian of the dynamic layer runs
// D_t (one linear layer + tanh over the W feature frames and γ(t)) and the decoders D_v, D_cov, D_o, D_c
// (two linear layers of 64, ReLU between, no biases; D_o and D_c also read the view direction), and writes the
// deformed, activated Gaussian into four RGBA32F render targets: (mean, opacity), scale, quaternion, colour.
// Features come from R16UI texture layers (the 10-bit codes as decoded, dequantised here), weights from one
// RGBA32F texture (each matrix row padded to whole texels).
import { type Attributes, fieldShapes } from "../container";
import type { SceneShape } from "../manifest";
import { UnsupportedError } from "../errors";
import {
  CODE_MAX,
  type Deformer,
  LayerRing,
  type Packed,
  WEIGHT_TEXTURE_WIDTH,
  dequantisation,
  packWeights,
  positionalEncoding,
} from "./deformer";
import { FULLSCREEN_VS, bindTextures, compile, floatTexture, framebuffer, rgba } from "./gl";

const MATRICES: [string, string][] = [
  ["temporal.weight", "mT"],
  ["d_pos.0.weight", "mP0"],
  ["d_pos.2.weight", "mP2"],
  ["d_cov.0.weight", "mC0"],
  ["d_cov.2.weight", "mC2"],
  ["d_opacity.0.weight", "mO0"],
  ["d_opacity.2.weight", "mO2"],
  ["d_color.0.weight", "mK0"],
  ["d_color.2.weight", "mK2"],
];

/** Where the weights live: one uniform block per matrix (needs uniform blocks as large as the largest matrix,
 * 17 KB at W = 3) or one float texture (any device). */
export type WeightStorage = "uniform" | "texture";

/** The fragment shader. Loops, not unrolled code: a fully unrolled field (about 5,000 dot products) crashed
 * SwiftShader's GPU process. */
function shader(shape: SceneShape, packed: Packed, storage: WeightStorage): string {
  const W = shape.window;
  const L = shape.peFreqs;
  const peVec = Math.ceil((2 * L) / 4);
  const inVec = W * 4 + peVec;
  const shapes = fieldShapes(W, L);
  const at = (name: string, index: string) => {
    const id = MATRICES.find(([n]) => n === name)![1];
    return storage === "uniform" ? `${id}[${index}]` : `w(${packed.offsets[name]![0]} + ${index})`;
  };
  const blocks =
    storage === "uniform"
      ? MATRICES.map(([name, id]) => {
          const [rows, cols] = shapes[name]!;
          return `layout(std140) uniform B_${id} { vec4 ${id}[${rows * Math.ceil(cols / 4)}]; };`;
        }).join("\n")
      : "";
  /** out[0..15] = act(M · (in[0..15] [, extra])) for a 64-row matrix. */
  const dense64 = (name: string, out: string, input: string, extra: string | null, act: string) => {
    const per = extra ? 17 : 16;
    return `  for (int j = 0; j < 16; j++) {
    vec4 v;
    for (int k = 0; k < 4; k++) {
      int row = (4 * j + k) * ${per};
      float acc = 0.0;
      for (int i = 0; i < 16; i++) acc += dot(${at(name, "row + i")}, ${input}[i]);
      ${extra ? `acc += dot(${at(name, "row + 16")}, ${extra});` : ""}
      v[k] = acc;
    }
    ${out}[j] = ${act};
  }`;
  };
  const head = (name: string, out: string, count: number) => `  for (int r = 0; r < ${count}; r++) {
    float acc = 0.0;
    for (int i = 0; i < 16; i++) acc += dot(${at(name, "r * 16 + i")}, a[i]);
    ${out}[r] = acc;
  }`;
  return `#version 300 es
precision highp float;
precision highp int;
precision highp usampler2DArray;
uniform highp sampler2D uX, uS, uQ, uC, uWt;
uniform usampler2DArray uF;
uniform int uLayer[${W}];
uniform float uLo[16];
uniform float uStep[16];
uniform vec4 uPe[${Math.max(1, peVec)}];
uniform vec3 uCam;
uniform int uSide;
${blocks}
layout(location = 0) out vec4 oMean;
layout(location = 1) out vec4 oScale;
layout(location = 2) out vec4 oQuat;
layout(location = 3) out vec4 oColor;
vec4 w(int i) { return texelFetch(uWt, ivec2(i % ${WEIGHT_TEXTURE_WIDTH}, i / ${WEIGHT_TEXTURE_WIDTH}), 0); }
void main() {
  ivec2 g = ivec2(gl_FragCoord.xy);
  vec4 x[${inVec}];
  for (int s = 0; s < ${W}; s++) {
    for (int q = 0; q < 4; q++) {
      vec4 v;
      for (int k = 0; k < 4; k++) {
        int c = 4 * q + k;
        uint code = texelFetch(uF, ivec3((c % 4) * uSide + g.x, (c / 4) * uSide + g.y, uLayer[s]), 0).r;
        v[k] = float(code) * uStep[c] + uLo[c];
      }
      x[4 * s + q] = v;
    }
  }
  for (int k = 0; k < ${peVec}; k++) x[${W * 4} + k] = uPe[k];
  vec4 h[16];
  for (int j = 0; j < 16; j++) {
    vec4 v;
    for (int k = 0; k < 4; k++) {
      int row = (4 * j + k) * ${inVec};
      float acc = 0.0;
      for (int i = 0; i < ${inVec}; i++) acc += dot(${at("temporal.weight", "row + i")}, x[i]);
      v[k] = acc;
    }
    h[j] = tanh(v);
  }
  vec4 a[16];
  float dpos[3];
  float dcov[7];
  float dop[1];
  float dcol[3];
${dense64("d_pos.0.weight", "a", "h", null, "max(v, vec4(0.0))")}
${head("d_pos.2.weight", "dpos", 3)}
${dense64("d_cov.0.weight", "a", "h", null, "max(v, vec4(0.0))")}
${head("d_cov.2.weight", "dcov", 7)}
  vec4 X = texelFetch(uX, g, 0);
  vec3 mean = X.xyz + vec3(dpos[0], dpos[1], dpos[2]);
  vec3 view = mean - uCam;
  vec4 vv = vec4(view / max(length(view), 1e-12), 0.0);
${dense64("d_opacity.0.weight", "a", "h", "vv", "max(v, vec4(0.0))")}
${head("d_opacity.2.weight", "dop", 1)}
${dense64("d_color.0.weight", "a", "h", "vv", "max(v, vec4(0.0))")}
${head("d_color.2.weight", "dcol", 3)}
  float opacity = clamp(1.0 / (1.0 + exp(-X.w)) + tanh(dop[0]), 0.0, 1.0);
  oMean = vec4(mean, opacity);
  oScale = vec4(exp(texelFetch(uS, g, 0).xyz + vec3(dcov[0], dcov[1], dcov[2])), 0.0);
  oQuat = texelFetch(uQ, g, 0) + vec4(dcov[3], dcov[4], dcov[5], dcov[6]);
  oColor = vec4(max(texelFetch(uC, g, 0).xyz, vec3(0.0)) + vec3(dcol[0], dcol[1], dcol[2]), 0.0);
}`;
}

export class DeformPass implements Deformer {
  readonly outputs: WebGLTexture[];
  private readonly program: WebGLProgram;
  private readonly fb: WebGLFramebuffer;
  private readonly canonical: WebGLTexture[];
  private readonly weights: WebGLTexture;
  readonly features: WebGLTexture;
  private readonly side: number;
  private lo: Float32Array = new Float32Array(16);
  private step: Float32Array = new Float32Array(16);
  private readonly ring: LayerRing;
  readonly kind: string;

  readonly storage: WeightStorage;
  private readonly blocks: WebGLBuffer[] = [];

  constructor(
    private readonly gl: WebGL2RenderingContext,
    private readonly shape: SceneShape,
    readonly ringLayers: number,
    storage?: WeightStorage,
  ) {
    const s = shape.side;
    this.side = s;
    const shapes = fieldShapes(shape.window, shape.peFreqs);
    const zeros = Object.fromEntries(
      Object.entries(shapes).map(([n, [r, c]]) => [`field.${n}`, new Float32Array(r * c)]),
    );
    const layout = packWeights(zeros, shape.window, shape.peFreqs);
    const largest = Math.max(...Object.values(shapes).map(([r, c]) => r * Math.ceil(c / 4) * 16));
    const fits =
      largest <= gl.getParameter(gl.MAX_UNIFORM_BLOCK_SIZE) &&
      MATRICES.length <= gl.getParameter(gl.MAX_FRAGMENT_UNIFORM_BLOCKS);
    if (storage === "uniform" && !fits)
      throw new UnsupportedError("the deformation weights do not fit this GPU's uniform blocks");
    // a texture by default: as fast as uniform blocks on SwiftShader (docs/BENCHMARKS.md, "Web player") and it
    // fits on every device
    this.storage = storage ?? "texture";
    this.program = compile(gl, FULLSCREEN_VS, shader(shape, layout, this.storage));
    if (this.storage === "uniform") {
      MATRICES.forEach(([, id], binding) => {
        const index = gl.getUniformBlockIndex(this.program, `B_${id}`);
        gl.uniformBlockBinding(this.program, index, binding);
        this.blocks.push(gl.createBuffer()!);
      });
    }
    this.outputs = [0, 1, 2, 3].map(() => floatTexture(gl, s, s, null));
    this.fb = framebuffer(gl, this.outputs);
    this.canonical = [0, 1, 2, 3].map(() => floatTexture(gl, s, s, null));
    this.weights = floatTexture(gl, WEIGHT_TEXTURE_WIDTH, layout.texels.length / 4 / WEIGHT_TEXTURE_WIDTH, null);
    this.features = gl.createTexture()!;
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.features);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.R16UI, 4 * s, 4 * s, ringLayers);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
      gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
    this.kind = `webgl2 (${this.storage} weights)`;
    this.ring = new LayerRing(ringLayers, (layer, codes) => {
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.features);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 2);
      gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, layer, 4 * s, 4 * s, 1, gl.RED_INTEGER, gl.UNSIGNED_SHORT, codes);
    });
  }

  /** A GOP's canonical attributes, weights and feature ranges (from its decoded keyframe). */
  loadGop(attributes: Attributes, floats: Record<string, Float32Array>): void {
    const gl = this.gl;
    const n = this.side * this.side;
    const x = rgba(attributes.position, 3, n);
    for (let i = 0; i < n; i++) x[4 * i + 3] = attributes.opacity[i]!;
    const data = [x, rgba(attributes.scale, 3, n), rgba(attributes.rotation, 4, n), rgba(attributes.color, 3, n)];
    data.forEach((d, i) => {
      gl.bindTexture(gl.TEXTURE_2D, this.canonical[i]!);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, this.side, this.side, gl.RGBA, gl.FLOAT, d);
    });
    const packed = packWeights(floats, this.shape.window, this.shape.peFreqs);
    if (this.storage === "uniform") {
      const shapes = fieldShapes(this.shape.window, this.shape.peFreqs);
      MATRICES.forEach(([name], binding) => {
        const [first, per] = packed.offsets[name]!;
        gl.bindBuffer(gl.UNIFORM_BUFFER, this.blocks[binding]!);
        gl.bufferData(
          gl.UNIFORM_BUFFER,
          packed.texels.subarray(4 * first, 4 * (first + shapes[name]![0] * per)),
          gl.STATIC_DRAW,
        );
      });
      gl.bindBuffer(gl.UNIFORM_BUFFER, null);
    } else {
      gl.bindTexture(gl.TEXTURE_2D, this.weights);
      gl.texSubImage2D(
        gl.TEXTURE_2D,
        0,
        0,
        0,
        WEIGHT_TEXTURE_WIDTH,
        packed.texels.length / 4 / WEIGHT_TEXTURE_WIDTH,
        gl.RGBA,
        gl.FLOAT,
        packed.texels,
      );
    }
    [this.lo, this.step] = dequantisation(floats["range.features"]!, CODE_MAX);
  }

  layer(gop: number, e: number, codes: () => Uint16Array): number {
    return this.ring.slot(gop, e, codes);
  }

  forget(): void {
    this.ring.forget();
  }

  async deform(frame: number, layers: number[], camera: ArrayLike<number>): Promise<Float32Array> {
    this.run(frame, layers, camera);
    const means = new Float32Array(4 * this.side * this.side);
    this.readMeans(means);
    return means;
  }

  /** Deform frame `frame` of the loaded GOP with the window's texture layers, seen from `camera` (its centre). */
  run(frame: number, layers: number[], camera: ArrayLike<number>): void {
    const gl = this.gl;
    const { gopSize, peFreqs } = this.shape;
    const pe = positionalEncoding(frame, gopSize, peFreqs);
    gl.useProgram(this.program);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fb);
    gl.viewport(0, 0, this.side, this.side);
    gl.disable(gl.BLEND);
    const p = this.program;
    bindTextures(gl, p, [
      ["uX", this.canonical[0]!],
      ["uS", this.canonical[1]!],
      ["uQ", this.canonical[2]!],
      ["uC", this.canonical[3]!],
      ["uWt", this.weights],
      ["uF", this.features, gl.TEXTURE_2D_ARRAY],
    ]);
    gl.uniform1iv(gl.getUniformLocation(p, "uLayer"), layers);
    gl.uniform1fv(gl.getUniformLocation(p, "uLo"), this.lo);
    gl.uniform1fv(gl.getUniformLocation(p, "uStep"), this.step);
    gl.uniform4fv(gl.getUniformLocation(p, "uPe"), pe);
    gl.uniform3f(gl.getUniformLocation(p, "uCam"), camera[0]!, camera[1]!, camera[2]!);
    gl.uniform1i(gl.getUniformLocation(p, "uSide"), this.side);
    this.blocks.forEach((b, binding) => {
      gl.bindBufferBase(gl.UNIFORM_BUFFER, binding, b);
    });
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  /** Wait for the GPU to finish what was submitted (a one-pixel read of the canvas). */
  sync(): void {
    const px = new Uint8Array(4);
    this.gl.readPixels(0, 0, 1, 1, this.gl.RGBA, this.gl.UNSIGNED_BYTE, px);
  }

  /** Read back (mean, opacity) of every dynamic Gaussian (the sort's input). */
  readMeans(out: Float32Array): void {
    const gl = this.gl;
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.fb);
    gl.readBuffer(gl.COLOR_ATTACHMENT0);
    gl.readPixels(0, 0, this.side, this.side, gl.RGBA, gl.FLOAT, out);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
  }
}
