// The viewer's camera (stgs/camera.py conventions: OpenCV pinhole, world-to-camera viewmat, x right, y down,
// z forward): an orbit around a target, flown with keys, or a scene camera's exact pose until the viewer moves.

/** A camera as the render passes take it. */
export interface View {
  /** World-to-camera, row-major 4x4 (OpenCV: x right, y down, z forward). */
  viewmat: Float64Array;
  /** fx, skew, cx, fy, cy for the render size. */
  K: [number, number, number, number, number];
  width: number;
  height: number;
}

/** The camera centre (world) of a row-major world-to-camera matrix. */
export function cameraCenter(viewmat: ArrayLike<number>): [number, number, number] {
  const c: [number, number, number] = [0, 0, 0];
  for (let i = 0; i < 3; i++)
    c[i] = -(viewmat[i]! * viewmat[3]! + viewmat[4 + i]! * viewmat[7]! + viewmat[8 + i]! * viewmat[11]!);
  return c;
}

export interface SceneCamera {
  name: string;
  width: number;
  height: number;
  K: number[][];
  viewmat: number[][];
}

type Vec3 = [number, number, number];
const sub = (a: Vec3, b: Vec3): Vec3 => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a: Vec3, b: Vec3): Vec3 => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a: Vec3, s: number): Vec3 => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a: Vec3, b: Vec3) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a: Vec3, b: Vec3): Vec3 => [
  a[1] * b[2] - a[2] * b[1],
  a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0],
];
const norm = (a: Vec3): Vec3 => scale(a, 1 / Math.max(Math.hypot(...a), 1e-12));

/** World-to-camera 4x4 (row-major) of a camera at `eye` looking at `target` (stgs.camera.look_at). */
export function lookAt(eye: Vec3, target: Vec3, up: Vec3): Float64Array {
  const forward = norm(sub(target, eye));
  let right = cross(forward, up);
  if (Math.hypot(...right) < 1e-9) right = cross(forward, [up[1], up[2], up[0]]);
  right = norm(right);
  const down = cross(forward, right);
  const m = new Float64Array(16);
  [right, down, forward].forEach((row, i) => {
    m.set(row, 4 * i);
    m[4 * i + 3] = -dot(row, eye);
  });
  m[15] = 1;
  return m;
}

/** A camera of cameras.json, checked (it comes from the network). */
export function parseSceneCameras(doc: unknown, maxCameras: number): SceneCamera[] {
  const d = doc as { format?: unknown; cameras?: unknown };
  if (typeof d !== "object" || d === null || d.format !== "streamstgs-cameras" || !Array.isArray(d.cameras)) {
    throw new Error("cameras.json is not a streamstgs-cameras document");
  }
  if (d.cameras.length > maxCameras) throw new Error(`cameras.json lists more than ${maxCameras} cameras`);
  return d.cameras.map((c: SceneCamera, i: number) => {
    const ok =
      typeof c.name === "string" &&
      Number.isInteger(c.width) &&
      Number.isInteger(c.height) &&
      c.width > 0 &&
      c.height > 0 &&
      Array.isArray(c.K) &&
      c.K.length === 3 &&
      c.K.every((r) => Array.isArray(r) && r.length === 3 && r.every(Number.isFinite)) &&
      Array.isArray(c.viewmat) &&
      c.viewmat.length === 4 &&
      c.viewmat.every((r) => Array.isArray(r) && r.length === 4 && r.every(Number.isFinite)) &&
      c.K[0]![0]! > 0 &&
      c.K[1]![1]! > 0;
    if (!ok) throw new Error(`cameras.json: camera ${i} is malformed`);
    return { name: c.name.slice(0, 100), width: c.width, height: c.height, K: c.K, viewmat: c.viewmat };
  });
}

/** Largest coordinate of an orbit target a link may carry. */
const POSE_LIMIT = 1e6;

export class ViewerCamera {
  target: Vec3 = [0, 0, 0];
  up: Vec3 = [0, 1, 0];
  yaw = 0;
  pitch = 0.2;
  radius = 3;
  fovX = 60;
  /** A scene camera's exact pose, used until the viewer moves. */
  pose: SceneCamera | null = null;

  eye(): Vec3 {
    const [u, f0] = this.basis();
    const r = norm(cross(f0, u));
    const dir = add(
      scale(f0, Math.cos(this.pitch) * Math.cos(this.yaw)),
      add(scale(r, Math.cos(this.pitch) * Math.sin(this.yaw)), scale(u, Math.sin(this.pitch))),
    );
    return add(this.target, scale(dir, this.radius));
  }

  /** (up, a horizontal reference direction) of the orbit. */
  private basis(): [Vec3, Vec3] {
    const u = norm(this.up);
    let f = cross(u, [1, 0, 0]);
    if (Math.hypot(...f) < 1e-6) f = cross(u, [0, 0, 1]);
    return [u, norm(cross(f, u))];
  }

  /** Point the orbit at the view a scene camera has (its centre as the eye, `distance` along its axis as target). */
  snap(cam: SceneCamera, distance: number): void {
    const v = cam.viewmat;
    const rows: Vec3[] = [0, 1, 2].map((i) => [v[i]![0], v[i]![1], v[i]![2]] as Vec3);
    const t: Vec3 = [v[0]![3]!, v[1]![3]!, v[2]![3]!];
    const center: Vec3 = [0, 1, 2].map(
      (i) => -(rows[0]![i]! * t[0] + rows[1]![i]! * t[1] + rows[2]![i]! * t[2]),
    ) as Vec3;
    this.target = add(center, scale(rows[2]!, distance));
    this.radius = distance;
    const [u, f0] = this.basis();
    const back = scale(rows[2]!, -1);
    this.pitch = Math.asin(Math.max(-1, Math.min(1, dot(back, u))));
    const r = norm(cross(f0, u));
    this.yaw = Math.atan2(dot(back, r), dot(back, f0));
    this.fovX = (2 * Math.atan(cam.width / 2 / cam.K[0]![0]!) * 180) / Math.PI;
    this.pose = cam;
  }

  orbit(dYaw: number, dPitch: number): void {
    this.pose = null;
    this.yaw += dYaw;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dPitch));
  }

  zoom(factor: number): void {
    this.pose = null;
    this.radius = Math.max(0.05, Math.min(1e4, this.radius * factor));
  }

  /** Move eye and target together along the view (forward), its right and the up vector. */
  fly(forward: number, right: number, upward: number): void {
    this.pose = null;
    const f = norm(sub(this.target, this.eye()));
    const r = norm(cross(f, this.up));
    const step = this.radius * 0.05;
    this.target = add(
      this.target,
      add(scale(f, forward * step), add(scale(r, right * step), scale(norm(this.up), upward * step))),
    );
  }

  /** The orbit as a link carries it: target x, y, z, yaw, pitch, radius, horizontal field of view (degrees). */
  orbitPose(): string {
    const values = [...this.target, this.yaw, this.pitch, this.radius, this.fovX];
    return values.map((v) => Number(v.toPrecision(7)).toString()).join(",");
  }

  /** Take the orbit a link carries (orbitPose's text); a malformed or out-of-range one throws and changes nothing. */
  setOrbitPose(text: string): void {
    const values = text.split(",").map(Number);
    if (values.length !== 7 || !values.every(Number.isFinite))
      throw new RangeError("the pose must be 7 finite numbers");
    const [x, y, z, yaw, pitch, radius, fov] = values as [number, number, number, number, number, number, number];
    if (Math.max(Math.abs(x), Math.abs(y), Math.abs(z)) > POSE_LIMIT) throw new RangeError("the target is too far out");
    if (Math.abs(yaw) > 1e3 || Math.abs(pitch) > 1.5) throw new RangeError("yaw or pitch out of range");
    if (!(radius >= 0.05 && radius <= 1e4)) throw new RangeError("the radius must be in 0.05..10000");
    if (!(fov >= 1 && fov <= 179)) throw new RangeError("the field of view must be in 1..179 degrees");
    this.pose = null;
    this.target = [x, y, z];
    [this.yaw, this.pitch, this.radius, this.fovX] = [yaw, pitch, radius, fov];
  }

  view(width: number, height: number): View {
    if (this.pose) {
      // the camera's view filling the canvas without distortion (one scale; at the camera's own size, its K)
      const c = this.pose;
      const s = Math.max(width / c.width, height / c.height);
      const dx = (width - c.width * s) / 2;
      const dy = (height - c.height * s) / 2;
      return {
        viewmat: Float64Array.from(c.viewmat.flat()),
        width,
        height,
        K: [c.K[0]![0]! * s, c.K[0]![1]! * s, c.K[0]![2]! * s + dx, c.K[1]![1]! * s, c.K[1]![2]! * s + dy],
      };
    }
    const f = (0.5 * width) / Math.tan((this.fovX * Math.PI) / 360);
    return { viewmat: lookAt(this.eye(), this.target, this.up), width, height, K: [f, 0, width / 2, f, height / 2] };
  }
}

/** The scene cameras' mean up direction (−y rows of their rotations), or world +y. */
export function sceneUp(cameras: SceneCamera[]): Vec3 {
  if (!cameras.length) return [0, 1, 0];
  const up = cameras.reduce<Vec3>(
    (a, c) => sub(a, [c.viewmat[1]![0]!, c.viewmat[1]![1]!, c.viewmat[1]![2]!]),
    [0, 0, 0],
  );
  return Math.hypot(...up) > 1e-6 ? norm(up) : [0, 1, 0];
}

/** The point the scene cameras look at most closely together (least squares over their axes), or the origin. */
export function sceneCenter(cameras: SceneCamera[]): Vec3 {
  if (cameras.length < 2) return [0, 0, 0];
  const A = [0, 0, 0, 0, 0, 0, 0, 0, 0];
  const b: Vec3 = [0, 0, 0];
  for (const c of cameras) {
    const v = c.viewmat;
    const d: Vec3 = [v[2]![0]!, v[2]![1]!, v[2]![2]!];
    const t: Vec3 = [v[0]![3]!, v[1]![3]!, v[2]![3]!];
    const o = [0, 1, 2].map((i) => -(v[0]![i]! * t[0] + v[1]![i]! * t[1] + v[2]![i]! * t[2])) as Vec3;
    for (let i = 0; i < 3; i++)
      for (let j = 0; j < 3; j++) {
        const p = (i === j ? 1 : 0) - d[i]! * d[j]!;
        A[3 * i + j]! += p;
        b[i]! += p * o[j]!;
      }
  }
  const det =
    A[0]! * (A[4]! * A[8]! - A[5]! * A[7]!) -
    A[1]! * (A[3]! * A[8]! - A[5]! * A[6]!) +
    A[2]! * (A[3]! * A[7]! - A[4]! * A[6]!);
  if (Math.abs(det) < 1e-9) return [0, 0, 0];
  const solve = (col: number): number => {
    const M = A.slice();
    for (let r = 0; r < 3; r++) M[3 * r + col] = b[r]!;
    return (
      (M[0]! * (M[4]! * M[8]! - M[5]! * M[7]!) -
        M[1]! * (M[3]! * M[8]! - M[5]! * M[6]!) +
        M[2]! * (M[3]! * M[7]! - M[4]! * M[6]!)) /
      det
    );
  };
  return [solve(0), solve(1), solve(2)];
}
