"""The packager's per-GOP work: prepare (sort, tile, keyframe, reference views), encode one ladder point, measure
it."""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.numpy import save_file as save_numpy

from stgs.camera import Camera, read_scene_cameras
from stgs.codec.features import (
    VIDEO_BITS,
    VIDEO_MAX,
    code_max,
    feature_ranges,
    features_from_frames,
    quantize_features,
    tile_frames,
)
from stgs.codec.keyframe import Keyframe, decode_keyframe, encode_keyframe
from stgs.codec.mp4 import set_timeline, split_fragmented
from stgs.codec.plas import permute_gop, plas_order, sort_key
from stgs.codec.plas_config import PLASConfig
from stgs.codec.quant import KEYFRAME_RUNGS, KeyframeQuant
from stgs.codec.video import FeatureCodec, VideoTiming, decode_segment, encode_gop
from stgs.fsio import load_png
from stgs.metrics import mse_psnr, psnr
from stgs.model.gop import GOPModel
from stgs.model.renderer import FrameRenderer, framing_orbit
from stgs.model.static import StaticLayer
from stgs.model.store import SceneMeta, load_gop
from stgs.picks import spread
from stgs.synth import load_ground_truth
from stgs.tree import CAMERAS, GROUND_TRUTH_DIR, TRAIN_REPORT, keyframe_rep_id


@dataclass
class PreparedGOP:
    """Everything a GOP's QP tasks share, computed once per GOP."""

    index: int
    frames: dict[int, np.ndarray]
    """(E, 4S, 4S) feature frames of the sorted GOP by code depth (12 always: the reference; 10 for AV1)."""
    ranges: torch.Tensor
    """(2, 16) feature ranges."""
    keyframe: bytes
    """The keyframe segment."""
    decoded_keyframe: Keyframe
    """The keyframe segment as a client decodes it."""
    views: list[tuple[int, Camera]]
    """(frame, camera) pairs the rendered-view PSNR uses."""
    reference: list[torch.Tensor]
    """Those views rendered from the uncompressed GOP."""
    model_mse: float | None = None
    """The uncompressed GOP's own mean squared error against the capture at the quality views (model_error), or
    None where the model dir does not tell."""
    lossy: dict[str, tuple[bytes, Keyframe]] = field(default_factory=dict)
    """The lossy keyframe rungs' segments and their decodes, by Representation id (stgs.tree.keyframe_rep_id)."""


@dataclass(frozen=True)
class QualityViews:
    """Where a pack measures each rung's rendered quality: cameras of the scene at their own resolution, and frames of
    each GOP."""

    cameras: list[Camera]
    source: str
    """held-out: the validation cameras the model dir names (stgs train); sample: the scene's cameras (its
    cameras.json, or a synthetic scene's ground truth) spread evenly; orbit: a framing orbit at 320x240, for a model
    with no cameras."""
    frames: list[int]
    """Frame indices within a GOP."""

    def pairs(self) -> list[tuple[int, Camera]]:
        return [(f, cam) for f in self.frames for cam in self.cameras]

    def describe(self) -> dict:
        """stats.json's `quality_views`."""
        return {"source": self.source, "cameras": [c.name for c in self.cameras],
                "sizes": [[c.width, c.height] for c in self.cameras], "frames": self.frames}


def scene_cameras(model_dir: Path) -> list[Camera]:
    """The scene's cameras as a pack offers them: the model dir's cameras.json (stgs train), else a synthetic scene's
    ground-truth cameras, else none."""
    if (model_dir / CAMERAS).is_file():
        return read_scene_cameras(model_dir)
    if (model_dir / GROUND_TRUTH_DIR / CAMERAS).is_file():
        return load_ground_truth(model_dir)[1]
    return []


def quality_views(model_dir: Path, meta: SceneMeta, model: Callable[[], GOPModel | StaticLayer], cameras: int,
                  frames: int | None) -> QualityViews:
    """The views rung quality is measured at (QualityViews): the model dir's held-out cameras where it names them,
    else `cameras` of the scene's cameras spread evenly, else (no cameras) an orbit framing `model()` (GOP 0, or a
    still's static layer); `frames` frames of each GOP spread evenly (None: every frame; a still has one)."""
    model_dir = Path(model_dir)
    every = [0] if meta.still else list(range(meta.shape.gop_size))
    picked = every if frames is None else spread(every, frames)
    scene = scene_cameras(model_dir)
    by_name = {c.name: c for c in scene}
    held = (meta.extra or {}).get("validation_cameras") or []
    if held and all(name in by_name for name in held):
        return QualityViews([by_name[name] for name in held], "held-out", picked)
    if scene:
        return QualityViews(spread(scene, cameras), "sample", picked)
    return QualityViews(framing_orbit(model(), cameras, 320, 240), "orbit", picked)


def lossy_rungs(names: tuple[str, ...]) -> dict[str, KeyframeQuant]:
    """Keyframe Representation id (stgs.tree.keyframe_rep_id) -> quantisation of each keyframe rung named
    (KEYFRAME_RUNGS)."""
    return {keyframe_rep_id(name): KEYFRAME_RUNGS[name] for name in names}


def prepare_gop(model_dir: Path, meta: SceneMeta, k: int, plas: PLASConfig | None, views: int, frames: int | None,
                static: StaticLayer | None = None, bits: tuple[int, ...] = (VIDEO_BITS,),
                keyframe_rungs: tuple[str, ...] = ()) -> PreparedGOP:
    """GOP k sorted (PLAS unless `plas` is None), tiled at each code depth of `bits` (each quantised from the float
    features), its keyframe written and read back (and one per lossy rung named in `keyframe_rungs`: KEYFRAME_RUNGS),
    and the reference views (quality_views: `views` cameras at `frames` frames) rendered from the uncompressed GOP
    (with the uncompressed static layer, if any)."""
    side = meta.shape.grid_side
    original = load_gop(model_dir, meta, k)
    if plas is not None:
        cfg = PLASConfig(**{**asdict(plas), "seed": plas.seed + k})
        model = permute_gop(original, plas_order(sort_key(original, cfg), side, cfg))
    else:
        model = original
    feats = model.features.detach()
    ranges = feature_ranges(feats)
    tiled = {b: tile_frames(quantize_features(feats, ranges, b), side).numpy().astype(np.uint16) for b in bits}
    keyframe = encode_keyframe(k, model, ranges)
    pairs = quality_views(model_dir, meta, lambda: original, views, frames).pairs()
    renderer = FrameRenderer(original, static=static)
    reference = [renderer.render(f, cam).clamp(0, 1) for f, cam in pairs]
    decoded = decode_keyframe(keyframe, meta.shape, k, max_bytes=len(keyframe))
    lossy = {}
    for rep, quant in lossy_rungs(keyframe_rungs).items():
        data = encode_keyframe(k, model, ranges, quant)
        lossy[rep] = (data, decode_keyframe(data, meta.shape, k, len(data), quant))
    return PreparedGOP(k, tiled, ranges, keyframe, decoded, pairs, reference,
                       model_error(model_dir, meta, k, pairs, reference), lossy)


def model_error(model_dir: Path, meta: SceneMeta, k: int, pairs: list[tuple[int, Camera]],
                reference: list[torch.Tensor]) -> float | None:
    """GOP k's own mean squared error against the capture, which every rung adds its own to: for a trained model
    the held-out PSNR its training report gives (stgs train), for a synthetic scene its renders `reference` of the
    views `pairs` against the ground-truth images; None where the model dir has neither."""
    model_dir = Path(model_dir)
    report = model_dir / TRAIN_REPORT
    if report.is_file():
        try:
            value = float(json.loads(report.read_text())["gops"][k]["val_psnr"])
        except (OSError, ValueError, KeyError, IndexError, TypeError):
            return None
        return 10 ** (-value / 10) if math.isfinite(value) else None
    if not (model_dir / GROUND_TRUTH_DIR / CAMERAS).is_file():
        return None
    doc = load_ground_truth(model_dir)[0]
    pattern = doc.get("pattern")
    if not isinstance(pattern, str):
        return None
    errors = []
    for (i, cam), image in zip(pairs, reference, strict=True):
        path = model_dir / GROUND_TRUTH_DIR / pattern.format(camera=cam.name, frame=k * meta.shape.gop_size + i)
        if not path.is_file():
            return None
        errors.append((image.double() - load_png(path).double()).square().mean().item())
    return sum(errors) / len(errors)


def save_prepared(gop: PreparedGOP, path: Path) -> None:
    """A prepared GOP as a safetensors file (no pickle) for the QP tasks that run elsewhere (stgs.packager.tasks);
    its keyframe is not in it: it is in the tree already."""
    tensors = {f"frames.{b}": f for b, f in gop.frames.items()} | {"ranges": gop.ranges.numpy()}
    tensors |= {f"reference.{i}": r.numpy() for i, r in enumerate(gop.reference)}
    views = [{"frame": f, "camera": cam.to_json()} for f, cam in gop.views]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    save_numpy(tensors, str(tmp), metadata={"index": str(gop.index), "views": json.dumps(views),
                                            "model_mse": json.dumps(gop.model_mse)})
    tmp.replace(path)


def load_prepared(path: Path, keyframe: bytes, meta: SceneMeta, lossy: dict[str, bytes] | None = None) -> PreparedGOP:
    """The prepared GOP `save_prepared` wrote, with its keyframe segment and those of its lossy keyframe rungs by
    Representation id (read from the tree)."""
    with safe_open(str(path), "np") as f:
        info = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open has no iterator
    k = int(info["index"])
    views = [(v["frame"], Camera.from_json(v["camera"])) for v in json.loads(info["views"])]
    reference = [torch.from_numpy(tensors[f"reference.{i}"]) for i in range(len(views))]
    decoded = decode_keyframe(keyframe, meta.shape, k, max_bytes=len(keyframe))
    frames = {int(name.split(".")[1]): t for name, t in tensors.items() if name.startswith("frames.")}
    quants = lossy_rungs(tuple(KEYFRAME_RUNGS))
    decoded_lossy = {rep: (data, decode_keyframe(data, meta.shape, k, len(data), quants[rep]))
                     for rep, data in (lossy or {}).items()}
    return PreparedGOP(k, frames, torch.from_numpy(tensors["ranges"]), keyframe, decoded, views, reference,
                       json.loads(info["model_mse"]), decoded_lossy)


class FeatureEncoder:
    """Encodes GOPs' feature frames at a ladder point into (init, media) placed on the Representation's timeline;
    every GOP of one Representation must give the same init segment."""

    def __init__(self, timing: VideoTiming, num_features: int, preset: Callable[[FeatureCodec], str],
                 loop_filters: bool = True):
        """preset: the encoder preset of each codec."""
        self.timing, self.num_features, self.preset, self.loop_filters = timing, num_features, preset, loop_filters
        self.init_segments: dict[str, bytes] = {}
        self._lock = threading.Lock()

    def encode(self, k: int, codec: FeatureCodec, q: int, frames: np.ndarray) -> tuple[bytes, bytes]:
        data = encode_gop(frames, q, self.timing, self.preset(codec), loop_filters=self.loop_filters, codec=codec)
        init, media = split_fragmented(data)
        media = set_timeline(media, k + 1, k * self.timing.segment_ticks(self.num_features))
        with self._lock:
            first = self.init_segments.setdefault(codec.rep_id(q), init)
        if first != init:
            raise RuntimeError(f"GOP {k} of {codec.rep_id(q)} produced a different init segment; "
                               "Representations need one init segment for all GOPs")
        return init, media


def measure(gop: PreparedGOP, codec: FeatureCodec, init: bytes, media: bytes, meta: SceneMeta,
            static: StaticLayer | None = None) -> dict:
    """Bytes, decoded-feature PSNR and rendered-view PSNR (see quality) of one media segment of `codec`; `static`:
    a layered scene's static layer as decoded from its segment (the PSNR is then the composite's)."""
    side = meta.shape.grid_side
    decoded = decode_segment(init, media, meta.shape.num_features, 4 * side, 4 * side, codec=codec)
    return {"bytes": len(media), **quality(gop, decoded, codec.bits, static)}


def quality(gop: PreparedGOP, frames: np.ndarray, bits: int, static: StaticLayer | None = None) -> dict:
    """Decoded-feature PSNR (the `bits`-bit codes of `frames` against the GOP's 12-bit codes, so a 10-bit set's
    figure includes its 10-bit step), rendered-view PSNR (of the mean squared error over the GOP's reference
    views, view_errors) and, where the GOP's own error is known, the PSNR a viewer gets against the capture,
    estimated as the sum of the two errors (`truth_psnr`; docs/PACKAGING.md, "Quality per rung"); all with the
    lossless keyframe, and under `keyframes` the two PSNRs with each lossy keyframe rung of the GOP instead."""
    feature_psnr = psnr(torch.from_numpy(frames.astype(np.float32)) / code_max(bits),
                        torch.from_numpy(gop.frames[VIDEO_BITS].astype(np.float32)) / VIDEO_MAX)
    features = features_from_frames(frames, frames.shape[-1] // 4, gop.ranges, bits)  # one decode for every rung
    out = {"feature_psnr": round(min(feature_psnr, 99.0), 4),
           **_view_psnrs(gop, render_errors(gop, gop.decoded_keyframe, features, static))}
    if gop.lossy:
        out["keyframes"] = {rep: _view_psnrs(gop, render_errors(gop, keyframe, features, static))
                            for rep, (_, keyframe) in gop.lossy.items()}
    return out


def _view_psnrs(gop: PreparedGOP, errors: list[float]) -> dict:
    out = {"render_psnr": round(mse_psnr(errors), 4)}
    if gop.model_mse is not None:
        out["truth_psnr"] = round(mse_psnr([gop.model_mse + sum(errors) / len(errors)]), 4)
    return out


def view_errors(gop: PreparedGOP, frames: np.ndarray, bits: int, static: StaticLayer | None = None) -> list[float]:
    """Mean squared error of each reference view (gop.views) rendered from the decoded GOP (its decoded keyframe and
    the `bits`-bit feature `frames`) against the uncompressed GOP's render."""
    features = features_from_frames(frames, frames.shape[-1] // 4, gop.ranges, bits)
    return render_errors(gop, gop.decoded_keyframe, features, static)


def render_errors(gop: PreparedGOP, keyframe: Keyframe, features: torch.Tensor,
                  static: StaticLayer | None = None) -> list[float]:
    """view_errors of the GOP drawn from `keyframe` and decoded (E, N, 16) `features`."""
    renderer = FrameRenderer(keyframe.to_model(features), static=static)
    return [(renderer.render(f, cam).clamp(0, 1).double() - ref.double()).square().mean().item()
            for (f, cam), ref in zip(gop.views, gop.reference, strict=True)]
