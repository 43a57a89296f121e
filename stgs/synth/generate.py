"""The generator behind `stgs synth`: ground-truth images and masks, the parameter-space fit, the model dir."""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from stgs.camera import Camera, orbit
from stgs.errors import StgsError
from stgs.fsio import DIR_MODE, atomic_write_bytes, load_png, save_png
from stgs.metrics import psnr
from stgs.model.gop import GOPShape
from stgs.model.renderer import FrameRenderer, in_guard_band
from stgs.model.static import StaticLayer
from stgs.model.store import load_model, load_static, save_model
from stgs.render import rasterize
from stgs.synth.config import SCENE_TARGET, SynthConfig
from stgs.synth.fit import fit_gop
from stgs.synth.scene import FOREGROUND, FoldedScene, ProceduralScene, TruthFrame
from stgs.tree import CAMERAS, GROUND_TRUTH_DIR, MASKS_DIR, MODEL_META


@dataclass
class SynthReport:
    """What `synthesize` measured."""

    fit: list[dict] = field(default_factory=list)
    """Per GOP: position/colour/opacity RMSE of the fit and its seconds."""
    fidelity_psnr: float = 0.0
    """Mean PSNR (dB) of model renders vs the ground-truth images."""
    fidelity_views: int = 0
    """Number of (frame, camera) views in that mean."""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def ground_truth_cameras(cfg: SynthConfig) -> list[Camera]:
    return orbit(cfg.num_cameras, radius=3.2, height=1.4, target=SCENE_TARGET, width=cfg.width,
                 height_px=cfg.height, prefix="cam")


def _draw(frames: list[TruthFrame], camera: Camera, colors: list[torch.Tensor] | None = None) -> torch.Tensor:
    cat = lambda key: torch.cat([getattr(t, key) for t in frames])  # noqa: E731
    colors = colors if colors is not None else [t.colors(camera.center) for t in frames]
    return rasterize(cat("means"), cat("quats"), cat("log_scales").exp(), cat("opacities"), torch.cat(colors),
                     camera.viewmat.float(), camera.K.float(), camera.width, camera.height)


def render_truth(scene: ProceduralScene, time_s: float, camera: Camera) -> torch.Tensor:
    """The true image (the static backdrop, if any, and the objects in one depth order). The backdrop is
    drawn with the model's guard band (stgs.model.renderer): beside a camera, a wall Gaussian seen at a grazing
    angle would otherwise veil the whole image."""
    frames = [scene.at(time_s)]
    if scene.static is not None:
        s = scene.static
        frames.append(dataclasses.replace(s, opacities=s.opacities * in_guard_band(s.means, camera).float()))
    return _draw(frames, camera)


def foreground_mask(scene: ProceduralScene, time_s: float, camera: Camera) -> torch.Tensor:
    """(H, W) bool: where the foreground objects alone cover more than half of a pixel."""
    t = scene.at(time_s)
    keep = torch.zeros(scene.capacity, dtype=torch.bool)
    for name in FOREGROUND:
        keep[scene.slices[name]] = True
    return _draw([t.select(keep)], camera, [torch.ones(int(keep.sum()), 3)])[..., 0] > 0.5


def imported_backdrop(cfg: SynthConfig) -> TruthFrame:
    """The backdrop of a 3DGS file (SynthConfig.static_from), view-independent, as the scene's truth."""
    from stgs.interop.static import import_static

    if cfg.static_from is None:
        raise ValueError("static_from: no 3DGS file given")
    matrix = None if cfg.static_transform is None else np.asarray(cfg.static_transform, np.float64).reshape(4, 4)
    layer, _ = import_static(Path(cfg.static_from), matrix)
    n = layer.capacity
    with torch.no_grad():
        return TruthFrame(layer.xyz.clone(), layer.log_scale.clone(), layer.rotation.clone(),
                          torch.sigmoid(layer.opacity_logit), torch.relu(layer.color), torch.zeros(n, 3),
                          torch.zeros(n, 3))


def truth_static_layer(scene: ProceduralScene) -> StaticLayer | None:
    """The backdrop as a static layer: the truth's attributes themselves (it never moves)."""
    if scene.static is None:
        return None
    layer = StaticLayer(len(scene.static.means))
    scene.static.copy_into(layer, 1e-6)
    return layer


def write_ground_truth(out: Path, scene: ProceduralScene, cfg: SynthConfig, cameras: list[Camera],
                       progress: bool) -> None:
    frames = cfg.num_gops * cfg.gop_size
    gt = out / GROUND_TRUTH_DIR
    for f in tqdm(range(frames), desc="ground truth", unit="frame", disable=not progress):
        for cam in cameras:
            save_png(gt / cam.name / f"{f:05d}.png", render_truth(scene, f / cfg.fps, cam))
            mask = foreground_mask(scene, f / cfg.fps, cam)
            save_png(gt / MASKS_DIR / cam.name / f"{f:05d}.png", mask[..., None].float().expand(-1, -1, 3))
    doc = {"fps": cfg.fps, "num_frames": frames, "pattern": "{camera}/{frame:05d}.png",
           "cameras": [c.to_json() for c in cameras]}
    atomic_write_bytes(gt / CAMERAS, (json.dumps(doc, indent=2) + "\n").encode())


def load_ground_truth(model_dir: Path) -> tuple[dict, list[Camera]]:
    """cameras.json of a synthetic model dir and its cameras."""
    path = Path(model_dir) / GROUND_TRUTH_DIR / CAMERAS
    if not path.is_file():
        raise StgsError(f"{model_dir}: no ground truth ({path} missing)")
    doc = json.loads(path.read_text())
    return doc, [Camera.from_json(c) for c in doc["cameras"]]


def measure_fidelity(model_dir: Path, stride: int = 5) -> tuple[float, int]:
    """Mean PSNR of the model's renders vs its stored ground truth, over every stride-th frame."""
    meta, gops = load_model(model_dir)
    static = load_static(model_dir, meta)
    doc, cameras = load_ground_truth(model_dir)
    values = []
    for k, gop in enumerate(gops):
        renderer = FrameRenderer(gop, static=static)
        for i in range(0, meta.shape.gop_size, stride):
            f = k * meta.shape.gop_size + i
            for cam in cameras:
                truth = load_png(Path(model_dir) / GROUND_TRUTH_DIR /
                                 doc["pattern"].format(camera=cam.name, frame=f))
                values.append(psnr(renderer.render(i, cam).clamp(0, 1), truth))
    return sum(values) / len(values), len(values)


def _replace_dir(staging: Path, out: Path) -> None:
    """Move a finished staging folder to `out`, replacing an older model dir there."""
    if out.exists():
        if not out.is_dir():
            raise StgsError(f"{out}: exists and is not a folder")
        if any(out.iterdir()) and not (out / MODEL_META).is_file():
            raise StgsError(f"{out}: folder is not empty and not a model dir; refusing to overwrite")
        old = out.with_name(f".{out.name}.old-{time.time_ns()}")
        out.rename(old)
        staging.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        staging.rename(out)


def synthesize(cfg: SynthConfig, out: Path, progress: bool = True) -> SynthReport:
    """Generate the scene, its ground truth and a fitted model dir at `out` (atomically)."""
    cfg.validate()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shape = GOPShape(capacity=cfg.grid_side ** 2, gop_size=cfg.gop_size, window=cfg.window)
    layered = "static_background" in cfg.effects
    scene = ProceduralScene(shape.capacity, tuple(cfg.effects), cfg.seed,
                            cfg.static_grid_side ** 2 if layered else 0)
    if cfg.static_from is not None:
        scene.static = imported_backdrop(cfg)
    fit_scene = FoldedScene(scene) if cfg.fold else scene
    if cfg.fold:
        shape = dataclasses.replace(shape, capacity=fit_scene.capacity)
    cameras = ground_truth_cameras(cfg)
    report = SynthReport()
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    staging.chmod(DIR_MODE)  # mkdtemp makes 0700
    try:
        write_ground_truth(staging, scene, cfg, cameras, progress)
        gops = []
        for k in tqdm(range(cfg.num_gops), desc="fit GOPs", unit="gop", disable=not progress):
            start = time.perf_counter()
            times = [(k * cfg.gop_size + i) / cfg.fps for i in range(cfg.gop_size)]
            result = fit_gop(fit_scene, times, shape, cfg.fit_steps, seed=cfg.seed + k,
                             smoothness=cfg.feature_smoothness)
            gops.append(result.model)
            report.fit.append({"gop": k, "position_rmse": result.position_rmse,
                               "color_rmse": result.color_rmse,
                               "opacity_rmse": result.opacity_rmse,
                               "seconds": time.perf_counter() - start})
        extra = {"generator": "stgs.synth", "config": dataclasses.asdict(cfg),
                 "ground_truth": GROUND_TRUTH_DIR}
        save_model(staging, gops, cfg.fps, extra, static=None if cfg.fold else truth_static_layer(scene))
        report.fidelity_psnr, report.fidelity_views = measure_fidelity(staging, cfg.fidelity_stride)
        atomic_write_bytes(staging / "synth_report.json",
                           (json.dumps(report.to_json(), indent=2) + "\n").encode())
        _replace_dir(staging, out)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return report
