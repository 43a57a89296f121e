"""A static layer from a 3DGS file trained elsewhere (`stgs train --static-from`, `stgs synth --static-from`).

Three things decide how a foreign file becomes our static layer, and `import_static` reports each:
- the frame: the file's Gaussians are moved into the cameras' frame by a similarity (scale, rotation,
  translation) given as a 4x4 matrix, or fitted (Umeyama's least squares) between the camera centres the file was
  trained with (the 3DGS `cameras.json` beside its PLY) and the dataset's cameras of the same names; identity when
  neither is given (the file was made in our frame, e.g. by `stgs export`);
- spherical harmonics above degree 1: folded into degrees 0 and 1 (stgs.interop.sh.fold), fitted over the
  directions the dataset's cameras see each Gaussian from when they are known, else dropped (the closest degree-1
  colour over the whole sphere);
- the capacity: a PLAS grid of side S holds S² Gaussians; S is the smallest that holds the file, the slots left
  over are padding (opacity 0, smallest scale), and a file larger than a side asked for keeps its S² most visible
  Gaussians (opacity x volume).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from stgs.camera import Camera
from stgs.errors import StgsError
from stgs.interop.files import read_splats
from stgs.interop.sh import degree1_coefficients, degree1_vectors, fold
from stgs.interop.splats import LOGIT_LIMIT, InteropError, Splats, to_static
from stgs.limits import MAX_CAPACITY
from stgs.model.static import StaticLayer

FOLD_CHUNK = 1 << 15
"""Gaussians folded at once (the fit holds cameras x 16 coefficients per Gaussian)."""


def check_similarity(matrix: np.ndarray, where: str) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) of a 4x4 similarity s·R·x + t (R a proper rotation); InteropError for anything else."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
        raise InteropError(f"{where}: a transform is a finite 4x4 matrix with last row 0 0 0 1")
    a = m[:3, :3]
    s = float(np.cbrt(np.linalg.det(a)))
    if not s > 0 or not np.allclose(a.T @ a, s * s * np.eye(3), rtol=1e-4, atol=1e-6 * s * s):
        raise InteropError(f"{where}: the transform is not a similarity (uniform scale, rotation, translation; "
                           "mirroring is not supported)")
    return s, a / s, m[:3, 3]


def read_transform(path: Path) -> np.ndarray:
    """A 4x4 matrix from a JSON file (a 4x4 list, or {"transform": ...}) or a text file of 16 numbers."""
    path = Path(path)
    try:
        text = path.read_text()
        try:
            doc = json.loads(text)
            values = doc["transform"] if isinstance(doc, dict) else doc
        except json.JSONDecodeError:
            values = [float(v) for v in text.split()]
        matrix = np.asarray(values, dtype=np.float64).reshape(4, 4)
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise InteropError(f"{path}: not a 4x4 transform ({exc})") from None
    check_similarity(matrix, str(path))
    return matrix


def read_camera_centres(path: Path) -> dict[str, np.ndarray]:
    """Camera name -> centre of the 3DGS cameras.json a file was trained with (entries with img_name and
    position; the name without its extension)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        return {Path(str(c["img_name"])).stem: np.asarray(c["position"], dtype=np.float64).reshape(3) for c in doc}
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InteropError(f"{path}: not a 3DGS cameras.json (a list of img_name and position) ({exc})") from None


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float]:
    """The 4x4 similarity taking points src (M, 3) closest to dst (M, 3) in least squares (Umeyama 1991), and the
    RMS distance left."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sigma, vt = np.linalg.svd(xd.T @ xs / len(src))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ flip @ vt
    scale = float((sigma * np.diag(flip)).sum() / (xs ** 2).sum(1).mean())
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = scale * rotation, mu_d - scale * rotation @ mu_s
    moved = src @ matrix[:3, :3].T + matrix[:3, 3]
    return matrix, float(np.sqrt(((moved - dst) ** 2).sum(1).mean()))


def fitted_transform(centres: dict[str, np.ndarray], cameras: list[Camera], where: str) -> tuple[np.ndarray, str]:
    names = [c.name for c in cameras if c.name in centres]
    if len(names) < 3:
        raise InteropError(f"{where}: {len(names)} of its cameras share a name with the dataset's; a fitted "
                           "transform needs three or more (or give the transform itself)")
    ours = {c.name: c.center.double().numpy() for c in cameras}
    src, dst = np.stack([centres[n] for n in names]), np.stack([ours[n] for n in names])
    if np.linalg.matrix_rank(src - src.mean(0), tol=1e-9 * max(1.0, np.abs(src).max())) < 2:
        raise InteropError(f"{where}: the matched camera centres are collinear; give the transform itself")
    matrix, rms = fit_similarity(src, dst)
    extent = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    if rms > 0.05 * extent:
        raise InteropError(f"{where}: the camera centres fit a similarity with {rms:.3g} RMS left, over 5 % of the "
                           f"rig's extent {extent:.3g}: the cameras do not match")
    return matrix, f"fitted from {len(names)} camera centres (RMS {rms:.3g}, rig extent {extent:.3g})"


def quat_of(rotation: np.ndarray) -> np.ndarray:
    """The unit wxyz quaternion of a rotation matrix."""
    w = math.sqrt(max(0.0, 1 + np.trace(rotation))) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + rotation[0, 0] - rotation[1, 1] - rotation[2, 2])) / 2,
                      rotation[2, 1] - rotation[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - rotation[0, 0] + rotation[1, 1] - rotation[2, 2])) / 2,
                      rotation[0, 2] - rotation[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - rotation[0, 0] - rotation[1, 1] + rotation[2, 2])) / 2,
                      rotation[1, 0] - rotation[0, 1])
    return np.array([w, x, y, z])


def transform(splats: Splats, matrix: np.ndarray) -> Splats:
    """`splats` (degree 0 or 1) moved by the similarity `matrix`: means, scales, rotations and the degree-1
    colour (a vector field of view directions, rotated with them)."""
    s, r, t = check_similarity(matrix, "transform")
    q = splats.quats.astype(np.float64)
    a = quat_of(r)
    w, x, y, z = q.T
    aw, ax, ay, az = a
    quats = np.stack([aw * w - ax * x - ay * y - az * z, aw * x + ax * w + ay * z - az * y,
                      aw * y - ax * z + ay * w + az * x, aw * z + ax * y - ay * x + az * w], 1)
    sh = splats.sh.astype(np.float64)
    if sh.shape[1] == 4:
        vectors = np.einsum("ij,njc->nic", r, degree1_vectors(sh[:, 1:4]))
        sh = np.concatenate([sh[:, :1], degree1_coefficients(vectors)], 1)
    means = splats.means.astype(np.float64) @ (s * r).T + t
    return Splats(means.astype(np.float32), (splats.log_scales + np.float32(math.log(s))).astype(np.float32),
                  quats.astype(np.float32), splats.opacity_logits.copy(), sh.astype(np.float32))


def fit_capacity(splats: Splats, side: int | None = None) -> tuple[Splats, int, int, int]:
    """(splats on a grid, its side S, slots padded, Gaussians dropped): S the smallest holding every Gaussian, or
    `side`; the rest padded at opacity 0; over S², the most visible (opacity x volume) kept, in file order."""
    n = splats.count
    side = side or math.isqrt(n - 1) + 1
    capacity = side * side
    if capacity > MAX_CAPACITY:
        raise InteropError(f"{n} Gaussians need a grid side of {side}, over the limit of {math.isqrt(MAX_CAPACITY)}: "
                           "ask for a smaller static grid side to keep the most visible")
    dropped = max(0, n - capacity)
    if dropped:
        logits = splats.opacity_logits.astype(np.float64)
        visibility = -np.logaddexp(0.0, -logits) + splats.log_scales.astype(np.float64).sum(1)  # log(o · volume)
        keep = np.sort(np.argsort(-visibility, kind="stable")[:capacity])
        splats = splats.select(keep)
    padded = capacity - splats.count
    if padded:
        pad = lambda a, fill: np.concatenate([a, np.broadcast_to(fill, (padded, *a.shape[1:]))])  # noqa: E731
        splats = Splats(pad(splats.means, splats.means[0]), pad(splats.log_scales, splats.log_scales.min(0)),
                        pad(splats.quats, np.array([1, 0, 0, 0], np.float32)),
                        pad(splats.opacity_logits, np.float32(-LOGIT_LIMIT)), pad(splats.sh, np.float32(0)))
    return splats, side, padded, dropped


def fold_over(splats: Splats, cameras: list[Camera] | None, matrix: np.ndarray | None, where: str) -> np.ndarray:
    """(N, 4, 3) float32: the file's coefficients folded to degree 1 over the directions from `cameras` (brought
    into the file's frame by the inverse of `matrix`), or dropped above degree 1 without cameras."""
    if not cameras:
        return fold(splats.sh).astype(np.float32)
    centres = np.stack([c.center.double().numpy() for c in cameras])
    if matrix is not None:
        s, r, t = check_similarity(matrix, where)
        centres = (centres - t) @ r / s
    out = np.empty((splats.count, 4, 3), dtype=np.float32)
    for lo in range(0, splats.count, FOLD_CHUNK):
        d = splats.means[lo:lo + FOLD_CHUNK].astype(np.float64)[:, None] - centres[None]
        dirs = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
        out[lo:lo + FOLD_CHUNK] = fold(splats.sh[lo:lo + FOLD_CHUNK], dirs)
    return out


def import_static(path: Path, matrix: np.ndarray | None = None, camera_centres: Path | None = None,
                  cameras: list[Camera] | None = None, side: int | None = None) -> tuple[StaticLayer, dict]:
    """The static layer of a PLY, SPZ or glb file, and a report of how it was made (the module's three answers).
    `matrix`: the file's frame to ours; `camera_centres`: the 3DGS cameras.json to fit it from instead;
    `cameras`: the dataset's (for the fit and for folding higher degrees over their directions); `side`: the grid
    side asked for (None: the smallest that holds the file)."""
    where = str(path)
    splats = read_splats(path)
    source = "identity (the file is in the cameras' frame)"
    if matrix is not None and camera_centres is not None:
        raise StgsError("give either a transform or the cameras to fit it from, not both")
    if camera_centres is not None:
        if not cameras:
            raise StgsError(f"{camera_centres}: fitting a transform needs the dataset's cameras")
        matrix, source = fitted_transform(read_camera_centres(camera_centres), cameras, where)
    elif matrix is not None:
        check_similarity(matrix, where)
        source = "given"
    degree = splats.sh_degree
    folded = "none"
    if degree > 1:
        sh = fold_over(splats, cameras, matrix, where)
        splats = Splats(splats.means, splats.log_scales, splats.quats, splats.opacity_logits, sh)
        folded = f"degree {degree} folded into 1, " + (f"fitted over {len(cameras)} cameras' directions" if cameras
                                                       else "higher degrees dropped")
    if matrix is not None:
        splats = transform(splats, matrix)
    splats, side, padded, dropped = fit_capacity(splats.check(where), side)
    report = {"file": where, "gaussians": splats.count - padded, "file_gaussians": splats.count - padded + dropped,
              "grid_side": side, "padded": padded, "dropped": dropped,
              "file_sh_degree": degree, "sh": folded, "transform": (np.eye(4) if matrix is None else matrix).tolist(),
              "transform_source": source}
    return to_static(splats), report
