"""Calibrating a still rig with COLMAP, through pycolmap (docs/CAPTURE.md, "Preparing raw footage").

The views of a few frames spread over the span are reconstructed together: one camera model per video, its
intrinsics shared by all of that video's frames (or a known lens, held fixed); features matched between the
cameras' views of one instant (the people in a scene move) and between one camera's views of different instants (a
rig does not), which ties them into one reconstruction. Incremental mapping is followed by robust bundle adjustment
(Cauchy loss, outlier observations dropped between rounds). Each camera's pose is the mean of its registered
views' poses. The reconstruction's similarity is then fixed: +Y up (against the cameras' mean image-down axis),
the origin at the point nearest every camera's optical axis (the rig's centre where the axes do not meet), and the
camera centres at a mean distance of RIG_RADIUS from their centroid.
"""

from __future__ import annotations

import itertools
import json
import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stgs.data.distortion import Intrinsics
from stgs.data.frames import write_png
from stgs.errors import StgsError
from stgs.prepare.settings import CAMERA_MODELS, DEFAULT_CAMERA_MODEL, RIG_RADIUS

SIFT_PEAK_THRESHOLD = 0.002
"""SIFT's contrast threshold: a third of COLMAP's default, so that dim, low-resolution rigs yield enough
features (docs/BENCHMARKS.md, "Captures")."""
MIN_CAMERAS = 3
ROBUST_SCALE_PX = 0.25
"""Scale of the Cauchy loss in the final bundle adjustments: residuals beyond a few times this weigh little."""
OUTLIER_PX = 1.0
"""Observations that reproject farther than this after a robust adjustment are dropped before the next."""
MIN_TRIANGULATION_DEG = 1.0
"""Points seen under a smaller angle are dropped with the outliers (their depth is unknown)."""
REFINE_ROUNDS = 4


class CalibrationError(StgsError):
    """The rig could not be calibrated: too few cameras registered, or a camera that did not."""


class LensFileError(StgsError):
    """A file of known lenses that cannot be used: not JSON, a lens with bad fields, a camera the footage lacks,
    a lens of another aspect ratio than its camera's frames."""


def read_lenses(path: Path, sizes: dict[str, tuple[int, int]]) -> dict[str, Intrinsics]:
    """Known lenses from `path`, per camera of `sizes` (name -> (width, height) of its upright frames), each
    resized to its camera's frames: {"lens": {...}} for every camera, {"cameras": {name: {...}}} for some or all
    (the others are fitted), or a prepare_report.json, whose fitted lenses are reused. A lens is
    Intrinsics.to_json's object."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LensFileError(f"{path}: cannot be read as JSON ({exc})") from None
    if isinstance(doc, dict) and isinstance(doc.get("calibration"), dict):
        doc = {"cameras": doc["calibration"].get("intrinsics")}
    if isinstance(doc, dict) and "lens" in doc:
        given = dict.fromkeys(sizes, doc["lens"])
    elif isinstance(doc, dict) and isinstance(doc.get("cameras"), dict):
        given = doc["cameras"]
        unknown = sorted(set(given) - set(sizes))
        if unknown:
            raise LensFileError(f"{path}: camera {unknown[0]!r} is not in the footage (its cameras: "
                                f"{', '.join(sizes)})")
    else:
        raise LensFileError(f'{path}: expected {{"lens": {{...}}}} or {{"cameras": {{name: {{...}}}}}}')
    lenses = {}
    for cam, d in given.items():
        if not isinstance(d, dict):
            raise LensFileError(f"{path}: camera {cam}: expected an object, got {d!r:.40}")
        try:
            lenses[cam] = Intrinsics.from_json(d).resized(*sizes[cam])
        except ValueError as exc:
            raise LensFileError(f"{path}: camera {cam}: {exc}") from None
    return lenses


@dataclass
class Calibration:
    """The rig, in the prepared frame: per camera its lens and its world-to-camera pose; the sparse points."""

    intrinsics: dict[str, Intrinsics]
    viewmats: dict[str, np.ndarray]
    """(4, 4) float64 world-to-camera, OpenCV axes."""
    points: np.ndarray
    """(P, 3) float64."""
    colours: np.ndarray
    """(P, 3) uint8 RGB."""
    report: dict = field(default_factory=dict)
    """registered, total, mean_reprojection_error, points, tracks (per camera), seconds, frames."""


def calibration_frames(span_frames: int, count: int) -> list[int]:
    """`count` frame indices spread evenly over a span of `span_frames` (each the middle of its share)."""
    count = max(1, min(count, span_frames))
    return sorted({int((i + 0.5) * span_frames / count) for i in range(count)})


def _silenced(pycolmap) -> Callable[[], None]:
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 3
    return lambda: setattr(pycolmap.logging, "minloglevel", level)


def _mean_rotation(rotations: list[np.ndarray]) -> np.ndarray:
    u, _, vt = np.linalg.svd(np.mean(rotations, axis=0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The shortest rotation taking unit vector a onto unit vector b."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1 + 1e-12:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def nearest_point_to_axes(centres: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """The point with the least squared distance to every line centre + t·axis; None where the lines are (near)
    parallel."""
    system = np.zeros((3, 3))
    rhs = np.zeros(3)
    for c, a in zip(centres, axes, strict=True):
        p = np.eye(3) - np.outer(a, a)
        system += p
        rhs += p @ c
    if np.linalg.cond(system) > 1e6:
        return None
    return np.linalg.solve(system, rhs)


def normalise(viewmats: dict[str, np.ndarray], points: np.ndarray,
              radius: float = RIG_RADIUS) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The rig and points in the prepared frame (+Y up, origin at the axes' meeting point, mean camera distance
    `radius` from the cameras' centroid)."""
    rots = np.stack([v[:3, :3] for v in viewmats.values()])
    centres = np.stack([-v[:3, :3].T @ v[:3, 3] for v in viewmats.values()])
    down = rots[:, 1, :].mean(0)
    if not np.linalg.norm(down) > 1e-9:
        raise CalibrationError("the cameras' image-down axes cancel out: no up direction can be set")
    turn = _rotation_between(-down / np.linalg.norm(down), np.array([0.0, 1.0, 0.0]))
    origin = nearest_point_to_axes(centres, rots[:, 2, :])
    if origin is None:
        origin = centres.mean(0)
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).mean())
    if not spread > 0:
        raise CalibrationError("the cameras stand at one point: the rig has no size to set")
    scale = radius / spread
    out = {}
    for name, v in viewmats.items():
        w = np.eye(4)
        w[:3, :3] = v[:3, :3] @ turn.T
        w[:3, 3] = scale * (v[:3, :3] @ origin + v[:3, 3])
        out[name] = w
    return out, (scale * (turn @ (points - origin).T).T if len(points) else points.reshape(0, 3))


def calibrate(views: dict[str, dict[int, np.ndarray]], camera_model: str = DEFAULT_CAMERA_MODEL,
              radius: float = RIG_RADIUS, work: Path | None = None,
              lenses: dict[str, Intrinsics] | None = None) -> Calibration:
    """Calibrate the rig from `views` (camera -> frame index -> (H, W, 3) uint8 RGB, the same frames for every
    camera) with pycolmap; `work` keeps COLMAP's database and images (a temporary folder otherwise). A camera in
    `lenses` keeps that lens (at its frames' size): only its pose is solved for; the others' are fitted as
    `camera_model`."""
    import pycolmap

    lenses = lenses or {}
    if camera_model not in CAMERA_MODELS:
        raise CalibrationError(f"camera model must be one of {', '.join(CAMERA_MODELS)}, not {camera_model!r}")
    if len(views) < MIN_CAMERAS:
        raise CalibrationError(f"{len(views)} cameras: calibration needs at least {MIN_CAMERAS}")
    with tempfile.TemporaryDirectory(prefix="stgs-colmap-") as scratch:
        root = Path(work or scratch)
        images = root / "images"
        names: dict[str, list[str]] = {}
        for cam, frames in views.items():
            for index, rgb in frames.items():
                name = f"{cam}/{index:06d}.png"
                write_png(images / name, rgb)
                names.setdefault(cam, []).append(name)
        database = root / "database.db"
        database.unlink(missing_ok=True)
        restore = _silenced(pycolmap)
        try:
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = camera_model
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.sift.peak_threshold = SIFT_PEAK_THRESHOLD
            extraction.num_threads = 1  # one thread throughout: the same footage gives the same calibration
            pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.PER_FOLDER,
                                      reader_options=reader, extraction_options=extraction)
            known = _give_lenses(pycolmap, database, lenses)
            instants = sorted({i for f in views.values() for i in f})
            pairs = root / "pairs.txt"
            # Across cameras only at one instant (people move); across instants only within a camera, whose
            # pose does not change: those matches tie each camera's views of different frames into one track.
            across = [f"{a}/{i:06d}.png {b}/{i:06d}.png" for i in instants for a, b in itertools.combinations(views, 2)]
            within = [f"{c}/{i:06d}.png {c}/{j:06d}.png" for c in views for i, j in itertools.combinations(instants, 2)]
            pairs.write_text("\n".join(across + within) + "\n")
            matching = pycolmap.FeatureMatchingOptions()
            matching.guided_matching = True
            matching.num_threads = 1
            pycolmap.match_image_pairs(database, matching_options=matching,
                                       pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs)))
            dropped_pairs = _drop_pairs_the_lenses_rule_out(pycolmap, database, known)
            options = pycolmap.IncrementalPipelineOptions()
            options.mapper.init_min_num_inliers = 30
            options.num_threads = 1
            options.mapper.num_threads = 1
            options.mapper.abs_pose_min_num_inliers = 15
            options.min_model_size = MIN_CAMERAS
            options.random_seed = 0
            options.mapper.random_seed = 0
            options.constant_cameras = known
            if known and len(known) == len(views):  # nothing to fit: registration must not refine them either
                options.ba_refine_focal_length = options.ba_refine_extra_params = False
                options.mapper.abs_pose_refine_focal_length = options.mapper.abs_pose_refine_extra_params = False
            (root / "sparse").mkdir(exist_ok=True)
            models = pycolmap.incremental_mapping(database, images, root / "sparse", options=options)
            best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
            refined = _refine(pycolmap, best, known) if best is not None else {}
        finally:
            restore()
        cal = _read_back(best, views, names, camera_model, radius, lenses)
        cal.report.update(refined, pairs_ruled_out_by_lenses=dropped_pairs)
        return cal


def _drop_pairs_the_lenses_rule_out(pycolmap, database: Path, known: set[int]) -> int:
    """Forget the verified matches between two cameras of known lenses that only a fundamental matrix explains
    (COLMAP's UNCALIBRATED pairs): with the lenses right, true matches fit an essential matrix. On repeated
    structure (a dome's panels) such pairs are chance alignments that place cameras at a symmetric pose. Their
    number."""
    if len(known) < 2:
        return 0
    db = pycolmap.Database.open(database)
    try:
        camera_of = {im.image_id: im.camera_id for im in db.read_all_images()}
        dropped = 0
        for pair, geometry in zip(*db.read_two_view_geometries(), strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pair)
            ca, cb = camera_of[a], camera_of[b]
            if (ca != cb and ca in known and cb in known
                    and geometry.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED):
                db.delete_two_view_geometry(a, b)
                dropped += 1
    finally:
        db.close()
    return dropped


def _refine(pycolmap, rec, constant: set[int]) -> dict:
    """Robust bundle adjustment of the mapper's reconstruction: Cauchy-weighted rounds, each followed by dropping
    the observations that still reproject farther than OUTLIER_PX, until none is dropped. The mapper's own
    adjustments are least squares, which the few bad tracks a scene always has (moving people, occlusion
    corners) pull away from the rig (docs/BENCHMARKS.md, "Captures"). Cameras in `constant` keep their lens."""
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = ROBUST_SCALE_PX
    options.ceres.solver_options.max_num_iterations = 200
    options.ceres.solver_options.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()  # the registered views do not change between rounds
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    for camera_id in constant:
        if camera_id in rec.cameras:
            config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    dropped, rounds = 0, 0
    while rounds < REFINE_ROUNDS and rec.num_points3D() >= 3:  # three points fix the gauge
        rounds += 1
        pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
        now = pycolmap.ObservationManager(rec).filter_all_points3D(OUTLIER_PX, MIN_TRIANGULATION_DEG)
        dropped += now
        if now == 0:
            break
    return {"refine_rounds": rounds, "observations_dropped": dropped}


def _give_lenses(pycolmap, database: Path, lenses: dict[str, Intrinsics]) -> set[int]:
    """Replace the database's cameras of the cameras in `lenses` (one folder each) by those lenses; their
    COLMAP camera ids."""
    if not lenses:
        return set()
    db = pycolmap.Database.open(database)
    try:
        ids = {im.name.split("/")[0]: im.camera_id for im in db.read_all_images()}
        for cam, lens in lenses.items():
            colmap = pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height,
                                     params=lens.colmap_params())
            colmap.camera_id = ids[cam]
            colmap.has_prior_focal_length = True
            db.update_camera(colmap)
    finally:
        db.close()
    return {ids[cam] for cam in lenses}


def _read_back(rec, views: dict[str, dict[int, np.ndarray]], names: dict[str, list[str]], camera_model: str,
               radius: float, lenses: dict[str, Intrinsics]) -> Calibration:
    total = len(views)
    by_name = {im.name: im for im in rec.images.values()} if rec is not None else {}
    poses: dict[str, list[np.ndarray]] = {}
    tracks: dict[str, int] = {}
    read: dict[str, Intrinsics] = {}
    for cam, files in names.items():
        for name in files:
            im = by_name.get(name)
            if im is None or not im.has_pose:
                continue
            poses.setdefault(cam, []).append(np.asarray(im.cam_from_world().matrix(), dtype=np.float64))
            tracks[cam] = tracks.get(cam, 0) + int(im.num_points3D)
            c = rec.cameras[im.camera_id]
            read[cam] = Intrinsics.from_colmap(c.model.name, int(c.width), int(c.height),
                                                 [float(p) for p in c.params])
    missing = [cam for cam in views if cam not in poses]
    hint = ("try more calibration frames (--calib-frames), more overlap between neighbouring cameras, or lock "
            "exposure and white balance")
    if len(poses) < MIN_CAMERAS:
        raise CalibrationError(f"COLMAP registered {len(poses)} of {total} cameras ({MIN_CAMERAS} needed); {hint}")
    if missing:
        raise CalibrationError(f"camera {missing[0]} did not register ({len(poses)} of {total} did"
                               f"{', also ' + ', '.join(missing[1:]) + ' did not' if missing[1:] else ''}); {hint}")
    viewmats = {}
    for cam in views:
        rot = _mean_rotation([p[:3, :3] for p in poses[cam]])
        centre = np.mean([-p[:3, :3].T @ p[:3, 3] for p in poses[cam]], axis=0)
        v = np.eye(4)
        v[:3, :3], v[:3, 3] = rot, -rot @ centre
        viewmats[cam] = v
    pts = rec.points3D.values()
    points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    colours = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    spread = {cam: float(np.degrees(max((_angle(p[:3, :3], viewmats[cam][:3, :3]) for p in poses[cam]),
                                        default=0.0))) for cam in views}
    viewmats, points = normalise(viewmats, points, radius)
    report = {"registered": len(poses), "total": total, "camera_model": camera_model,
              "lenses": {cam: "given" if cam in lenses else "fitted" for cam in views},
              "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
              "points": len(points), "tracks": tracks, "pose_spread_deg": spread,
              "rig_radius": radius}
    return Calibration(read, viewmats, points, colours, report)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(a @ b.T)) - 1) / 2)))


def rig_errors(ours: dict[str, np.ndarray], truth: dict[str, np.ndarray],
               inlier_deg: float = 2.0) -> dict[str, tuple[float, float]]:
    """Per camera of `truth`, (rotation error in degrees, centre error in % of the rig's radius) of `ours` after
    the similarity that best fits it to the truth: the rotation that aligns the most cameras' orientations to
    within `inlier_deg` (refined on those), then the scale and shift that best align their centres (both
    world-to-camera, OpenCV axes). A few cameras placed badly do not spoil the fit of the others. A camera `ours`
    lacks is absent from the result."""
    names = [n for n in truth if n in ours]
    if len(names) < 2:
        raise ValueError("comparing rigs needs two cameras in both")

    def misfit(turn: np.ndarray) -> np.ndarray:
        return np.array([math.degrees(_angle(ours[n][:3, :3] @ turn.T, truth[n][:3, :3])) for n in names])

    candidates = [truth[n][:3, :3].T @ ours[n][:3, :3] for n in names]
    best = max(candidates, key=lambda t: int((misfit(t) <= inlier_deg).sum()))
    keep = misfit(best) <= inlier_deg
    if keep.sum() < 2:  # no two cameras agree: fit them all
        keep[:] = True
    turn = _mean_rotation([c for c, k in zip(candidates, keep, strict=True) if k])
    a = np.stack([turn @ (-ours[n][:3, :3].T @ ours[n][:3, 3]) for n in names])
    b = np.stack([-truth[n][:3, :3].T @ truth[n][:3, 3] for n in names])
    a0, b0 = a - a[keep].mean(0), b - b[keep].mean(0)
    scale = float((a0[keep] * b0[keep]).sum() / (a0[keep] * a0[keep]).sum())
    radius = float(np.linalg.norm(b - b.mean(0), axis=1).mean())
    rotations = misfit(turn)
    return {n: (float(rotations[i]), float(np.linalg.norm(scale * a0[i] - b0[i])) / radius * 100)
            for i, n in enumerate(names)}
