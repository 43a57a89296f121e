// WebGL2 plumbing: context, programs, float textures and framebuffers.
import { UnsupportedError } from "../errors";

export interface GLContext {
  gl: WebGL2RenderingContext;
  /** RGBA32F blending (EXT_float_blend); without it the accumulation target is RGBA16F. */
  floatBlend: boolean;
  timer: { ext: object; query: number } | null;
}

export function createContext(canvas: HTMLCanvasElement): GLContext {
  const gl = canvas.getContext("webgl2", {
    antialias: false,
    alpha: false,
    depth: false,
    stencil: false,
    premultipliedAlpha: false,
    preserveDrawingBuffer: true,
    powerPreference: "high-performance",
  });
  if (!gl) throw new UnsupportedError("this browser has no WebGL2");
  if (!gl.getExtension("EXT_color_buffer_float"))
    throw new UnsupportedError("this browser's WebGL2 cannot render to float textures (EXT_color_buffer_float)");
  const floatBlend = gl.getExtension("EXT_float_blend") !== null;
  return { gl, floatBlend, timer: null };
}

export function compile(gl: WebGL2RenderingContext, vs: string, fs: string): WebGLProgram {
  const program = gl.createProgram()!;
  for (const [type, src] of [
    [gl.VERTEX_SHADER, vs],
    [gl.FRAGMENT_SHADER, fs],
  ] as const) {
    const shader = gl.createShader(type)!;
    gl.shaderSource(shader, src);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error(`shader does not compile: ${gl.getShaderInfoLog(shader)}`);
    }
    gl.attachShader(program, shader);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS))
    throw new Error(`program does not link: ${gl.getProgramInfoLog(program)}`);
  return program;
}

/** An RGBA32F texture of side x rows texels, nearest filtering, filled from `data` when given. */
export function floatTexture(
  gl: WebGL2RenderingContext,
  width: number,
  height: number,
  data: Float32Array | null,
): WebGLTexture {
  const tex = gl.createTexture()!;
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, width, height);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  if (data) gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, width, height, gl.RGBA, gl.FLOAT, data);
  return tex;
}

/** (N, C) values -> N RGBA texels (missing channels 0), padded to width x height. */
export function rgba(values: Float32Array, channels: number, texels: number): Float32Array {
  const out = new Float32Array(texels * 4);
  const n = values.length / channels;
  for (let i = 0; i < n; i++) for (let c = 0; c < channels; c++) out[4 * i + c] = values[channels * i + c]!;
  return out;
}

export function framebuffer(gl: WebGL2RenderingContext, textures: WebGLTexture[]): WebGLFramebuffer {
  const fb = gl.createFramebuffer()!;
  gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
  textures.forEach((t, i) => {
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, t, 0);
  });
  gl.drawBuffers(textures.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
  const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
  if (status !== gl.FRAMEBUFFER_COMPLETE)
    throw new UnsupportedError(`float framebuffer incomplete (0x${status.toString(16)})`);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  return fb;
}

export function bindTextures(
  gl: WebGL2RenderingContext,
  program: WebGLProgram,
  textures: [string, WebGLTexture, number?][],
): void {
  textures.forEach(([name, tex, target], unit) => {
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(target ?? gl.TEXTURE_2D, tex);
    gl.uniform1i(gl.getUniformLocation(program, name), unit);
  });
}

/** A vertex shader drawing one triangle over the whole target (a full-screen pass). */
export const FULLSCREEN_VS = `#version 300 es
void main() { vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2)); gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0); }`;
