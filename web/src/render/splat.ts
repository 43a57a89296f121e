// The splat pass (the splatter numerics of docs/ARCHITECTURE.md, as far as a rasteriser allows; docs/WEB.md lists the
// deviations): one instanced quad per visible Gaussian in the sort's front-to-back order, sized by the
// opacity-aware screen extent; the vertex shader projects with EWA (Σ' = J W Σ Wᵀ Jᵀ + 0.3 px²) exactly as
// stgs/render/project.py does, the fragment shader evaluates alpha = min(0.99, o·exp(−½ dᵀΣ'⁻¹d)) at the pixel
// centre and discards alpha < 1/255, and "under" blending (ONE_MINUS_DST_ALPHA, ONE) composites front to back
// into a float target holding (Σ c·α·T, 1 − T). A last pass adds T·background.
import { type View, cameraCenter } from "../camera";
import type { Attributes } from "../container";
import { FULLSCREEN_VS, bindTextures, compile, floatTexture, framebuffer } from "./gl";

const SPLAT_VS = `#version 300 es
precision highp float;
precision highp int;
uniform highp sampler2D uSMean, uSScale, uSQuat, uSColor, uSh0, uSh1, uSh2;
uniform highp sampler2D uDMean, uDScale, uDQuat, uDColor;
uniform int uStaticCount, uStaticSide, uDynSide, uShDegree;
uniform vec3 uR0, uR1, uR2, uT, uCam;
uniform vec4 uK; // fx, skew, cx, fy
uniform float uCy;
uniform vec2 uSize;
in uint aId;
flat out vec2 vMean;
flat out vec3 vConic;
flat out float vOpacity;
flat out vec3 vColor;
const float NEAR_Z = 0.01;
const float BLUR = 0.3;
mat3 rotation(vec4 q) {
  float peak = max(max(abs(q.x), abs(q.y)), max(abs(q.z), abs(q.w)));
  if (peak == 0.0) return mat3(1.0);
  q = q / peak;
  q = q / length(q);
  float w = q.x, x = q.y, y = q.z, z = q.w;
  // columns of the row-major matrix of stgs/render/project.py quat_to_rotmat
  return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
              2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
              2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
}
void cull() { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); vOpacity = 0.0; }
void main() {
  int id = int(aId);
  vec4 mo; vec3 scale; vec4 quat; vec3 color;
  if (id < uStaticCount) {
    ivec2 g = ivec2(id % uStaticSide, id / uStaticSide);
    mo = texelFetch(uSMean, g, 0); scale = texelFetch(uSScale, g, 0).xyz; quat = texelFetch(uSQuat, g, 0);
    color = texelFetch(uSColor, g, 0).xyz;
    if (uShDegree > 0) {
      vec3 d = mo.xyz - uCam;
      d = d / max(length(d), 1e-12);
      color += d.x * texelFetch(uSh0, g, 0).xyz + d.y * texelFetch(uSh1, g, 0).xyz + d.z * texelFetch(uSh2, g, 0).xyz;
    }
  } else {
    int j = id - uStaticCount;
    ivec2 g = ivec2(j % uDynSide, j / uDynSide);
    mo = texelFetch(uDMean, g, 0); scale = texelFetch(uDScale, g, 0).xyz; quat = texelFetch(uDQuat, g, 0);
    color = texelFetch(uDColor, g, 0).xyz;
  }
  vec3 p = vec3(dot(uR0, mo.xyz), dot(uR1, mo.xyz), dot(uR2, mo.xyz)) + uT;
  float level = 255.0 * mo.w;
  if (p.z < NEAR_Z || level < 1.0) { cull(); return; }
  float xn = p.x / p.z, yn = p.y / p.z;
  vec2 mean = vec2(uK.x * xn + uK.y * yn + uK.z, uK.w * yn + uCy);
  vec3 dn0 = vec3(1.0 / p.z, 0.0, -xn / p.z);
  vec3 dn1 = vec3(0.0, 1.0 / p.z, -yn / p.z);
  vec3 j0 = uK.x * dn0 + uK.y * dn1;
  vec3 j1 = uK.w * dn1;
  mat3 A = rotation(quat);
  vec3 m1, m2;
  for (int k = 0; k < 3; k++) {
    vec3 col = A[k] * scale[k];
    vec3 cam = vec3(dot(uR0, col), dot(uR1, col), dot(uR2, col));
    m1[k] = dot(j0, cam);
    m2[k] = dot(j1, cam);
  }
  float a0 = dot(m1, m1), b0 = dot(m1, m2), c0 = dot(m2, m2);
  vec3 minors = vec3(m1.x * m2.y - m1.y * m2.x, m1.x * m2.z - m1.z * m2.x, m1.y * m2.z - m1.z * m2.y);
  float det = dot(minors, minors) + BLUR * (a0 + c0) + BLUR * BLUR;
  vConic = vec3((c0 + BLUR) / det, -b0 / det, (a0 + BLUR) / det);
  float quad = 2.0 * log(level);
  vec2 extent = sqrt(quad * vec2(a0 + BLUR, c0 + BLUR)) * (1.0 + 1e-4) + 1e-3;
  vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1)) * 2.0 - 1.0;
  vec2 pixel = mean + corner * extent;
  gl_Position = vec4(pixel.x / uSize.x * 2.0 - 1.0, 1.0 - pixel.y / uSize.y * 2.0, 0.0, 1.0);
  vMean = mean;
  vOpacity = mo.w;
  vColor = color;
}`;

const SPLAT_FS = `#version 300 es
precision highp float;
flat in vec2 vMean;
flat in vec3 vConic;
flat in float vOpacity;
flat in vec3 vColor;
uniform float uHeight;
out vec4 outColor;
void main() {
  vec2 d = vec2(gl_FragCoord.x, uHeight - gl_FragCoord.y) - vMean;
  float q = vConic.x * d.x * d.x + 2.0 * vConic.y * d.x * d.y + vConic.z * d.y * d.y;
  float alpha = min(0.99, vOpacity * exp(-0.5 * q));
  if (alpha < 1.0 / 255.0) discard;
  outColor = vec4(vColor * alpha, alpha);
}`;

const COMPOSITE_FS = `#version 300 es
precision highp float;
uniform highp sampler2D uAccum;
uniform vec3 uBackground;
out vec4 outColor;
void main() {
  vec4 acc = texelFetch(uAccum, ivec2(gl_FragCoord.xy), 0);
  outColor = vec4(clamp(acc.rgb + (1.0 - acc.a) * uBackground, 0.0, 1.0), 1.0);
}`;

export interface StaticTextures {
  count: number;
  side: number;
  shDegree: number;
  textures: WebGLTexture[];
}

/** The static layer's activated attributes as textures: (mean, sigmoid(opacity)), exp(scale), quaternion,
 * relu(colour), and the three sh1 rows. */
export function staticTextures(
  gl: WebGL2RenderingContext,
  attrs: Attributes,
  count: number,
  side: number,
  shDegree: number,
): StaticTextures {
  const f = Math.fround;
  const mean = new Float32Array(count * 4);
  const scale = new Float32Array(count * 4);
  const quat = new Float32Array(count * 4);
  const color = new Float32Array(count * 4);
  for (let i = 0; i < count; i++) {
    for (let c = 0; c < 3; c++) {
      mean[4 * i + c] = attrs.position[3 * i + c]!;
      scale[4 * i + c] = f(Math.exp(attrs.scale[3 * i + c]!));
      color[4 * i + c] = Math.max(0, attrs.color[3 * i + c]!);
    }
    mean[4 * i + 3] = f(1 / (1 + Math.exp(-attrs.opacity[i]!)));
    for (let c = 0; c < 4; c++) quat[4 * i + c] = attrs.rotation[4 * i + c]!;
  }
  const sh = shDegree
    ? ["sh1_x", "sh1_y", "sh1_z"].map((name) => {
        const out = new Float32Array(count * 4);
        for (let i = 0; i < count; i++) for (let c = 0; c < 3; c++) out[4 * i + c] = attrs[name]![3 * i + c]!;
        return out;
      })
    : [];
  const textures = [mean, scale, quat, color, ...sh].map((d) => floatTexture(gl, side, side, d));
  return { count, side, shDegree, textures };
}

export class SplatPass {
  private readonly splat: WebGLProgram;
  private readonly composite: WebGLProgram;
  private readonly vao: WebGLVertexArrayObject;
  private readonly ids: WebGLBuffer;
  private accum: WebGLTexture | null = null;
  private fb: WebGLFramebuffer | null = null;
  private size = [0, 0];
  private readonly empty: WebGLTexture;

  constructor(
    private readonly gl: WebGL2RenderingContext,
    private readonly floatBlend: boolean,
  ) {
    this.splat = compile(gl, SPLAT_VS, SPLAT_FS);
    this.composite = compile(gl, FULLSCREEN_VS, COMPOSITE_FS);
    this.vao = gl.createVertexArray()!;
    this.ids = gl.createBuffer()!;
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.ids);
    const loc = gl.getAttribLocation(this.splat, "aId");
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribIPointer(loc, 1, gl.UNSIGNED_INT, 4, 0);
    gl.vertexAttribDivisor(loc, 1);
    gl.bindVertexArray(null);
    this.empty = floatTexture(gl, 1, 1, new Float32Array(4));
  }

  private target(width: number, height: number): void {
    if (this.size[0] === width && this.size[1] === height) return;
    const gl = this.gl;
    if (this.accum) gl.deleteTexture(this.accum);
    if (this.fb) gl.deleteFramebuffer(this.fb);
    this.accum = gl.createTexture()!;
    gl.bindTexture(gl.TEXTURE_2D, this.accum);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.floatBlend ? gl.RGBA32F : gl.RGBA16F, width, height);
    // one level: the default mipmapped filter would leave the texture incomplete (texelFetch reads zeros)
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    this.fb = framebuffer(gl, [this.accum]);
    this.size = [width, height];
  }

  /** Wait for the GPU to finish what was drawn (a one-pixel read of the canvas): exact per-stage times. */
  sync(): void {
    this.gl.readPixels(0, 0, 1, 1, this.gl.RGBA, this.gl.UNSIGNED_BYTE, new Uint8Array(4));
  }

  /** Splat the Gaussians `order` names (static ids first, then the dynamic layer's; a still scene has no dynamic
   * textures) and composite over `background`. */
  draw(
    view: View,
    order: Uint32Array,
    count: number,
    layer: StaticTextures | null,
    dynamic: WebGLTexture[],
    dynSide: number,
    background: [number, number, number],
  ): void {
    const gl = this.gl;
    const { width, height, viewmat: m, K } = view;
    this.target(width, height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fb);
    gl.viewport(0, 0, width, height);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.enable(gl.BLEND);
    gl.blendEquation(gl.FUNC_ADD);
    gl.blendFuncSeparate(gl.ONE_MINUS_DST_ALPHA, gl.ONE, gl.ONE_MINUS_DST_ALPHA, gl.ONE);
    gl.useProgram(this.splat);
    const p = this.splat;
    const s = layer?.textures ?? [];
    bindTextures(gl, p, [
      ["uSMean", s[0] ?? this.empty],
      ["uSScale", s[1] ?? this.empty],
      ["uSQuat", s[2] ?? this.empty],
      ["uSColor", s[3] ?? this.empty],
      ["uSh0", s[4] ?? this.empty],
      ["uSh1", s[5] ?? this.empty],
      ["uSh2", s[6] ?? this.empty],
      ["uDMean", dynamic[0] ?? this.empty],
      ["uDScale", dynamic[1] ?? this.empty],
      ["uDQuat", dynamic[2] ?? this.empty],
      ["uDColor", dynamic[3] ?? this.empty],
    ]);
    const u = (name: string) => gl.getUniformLocation(p, name);
    gl.uniform1i(u("uStaticCount"), layer?.count ?? 0);
    gl.uniform1i(u("uStaticSide"), layer?.side ?? 1);
    gl.uniform1i(u("uDynSide"), dynSide);
    gl.uniform1i(u("uShDegree"), layer?.shDegree ?? 0);
    gl.uniform3f(u("uR0"), m[0]!, m[1]!, m[2]!);
    gl.uniform3f(u("uR1"), m[4]!, m[5]!, m[6]!);
    gl.uniform3f(u("uR2"), m[8]!, m[9]!, m[10]!);
    gl.uniform3f(u("uT"), m[3]!, m[7]!, m[11]!);
    const c = cameraCenter(m);
    gl.uniform3f(u("uCam"), c[0], c[1], c[2]);
    gl.uniform4f(u("uK"), K[0], K[1], K[2], K[3]);
    gl.uniform1f(u("uCy"), K[4]);
    gl.uniform2f(u("uSize"), width, height);
    gl.uniform1f(u("uHeight"), height);
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.ids);
    gl.bufferData(gl.ARRAY_BUFFER, order.subarray(0, count), gl.STREAM_DRAW);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, count);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, width, height);
    gl.useProgram(this.composite);
    bindTextures(gl, this.composite, [["uAccum", this.accum!]]);
    gl.uniform3f(gl.getUniformLocation(this.composite, "uBackground"), ...background);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }
}
