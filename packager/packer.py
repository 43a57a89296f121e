"""`stgs pack MODEL_DIR OUT_DIR`: a model dir -> a DASH tree (manifests/PROFILE.md).

Per GOP: PLAS-sort the Gaussians, write the keyframe segment (attribute
images, weights, ranges), tile the 12-bit features into frames; per GOP and
QP: encode the feature video, cut it into init + media segment and place the
segment on the Representation's timeline; then measure every segment (bytes,
decoded-feature PSNR, rendered-view PSNR against the uncompressed model) and
write stats.json and, last, manifest.mpd.

All segment files live under a folder named after a digest of the inputs and
settings (`v-<id>/`), so a re-pack of the same inputs writes the same bytes
under the same names and a re-pack of different inputs writes new names:
content under a URL never changes.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from stgs.camera import Camera
from stgs.codec.features import VIDEO_MAX, feature_ranges, features_from_frames, quantize_features, tile_frames
from stgs.codec.keyframe import Keyframe, decode_keyframe, encode_keyframe
from stgs.codec.mp4 import hevc_codecs, set_timeline, split_fragmented
from stgs.codec.plas import PLASConfig, permute_gop, plas_order, sort_key
from stgs.codec.video import PRESETS, VideoTiming, decode_segment, encode_gop, require_ffmpeg
from stgs.errors import FieldError, StgsError
from stgs.fsio import atomic_write_bytes
from stgs.metrics import psnr
from stgs.model.gop import GOPModel
from stgs.model.store import SceneMeta, load_gop, read_meta
from stgs.model.view import FrameRenderer, framing_orbit
from stgs.mpd import (
    FEATURE_SCHEME,
    KEYFRAME_SCHEME,
    MPD,
    AdaptationSet,
    Descriptor,
    Period,
    Representation,
    SegmentTemplate,
)
from stgs.synth import load_ground_truth
from stgs.tree import (
    CAMERAS,
    CAMERAS_FORMAT,
    GROUND_TRUTH_DIR,
    KEYFRAME_MIME_TYPE,
    KEYFRAME_REP,
    MANIFEST,
    MODEL_META,
    PACK_STATE,
    STATS,
    feature_init_template,
    feature_media_template,
    feature_path,
    keyframe_path,
    keyframe_template,
    rep_id,
    version_dir,
)

DEFAULT_QPS = (16, 20, 24, 28, 32)


@dataclass
class PackConfig:
    """Settings of one pack run."""

    qps: tuple[int, ...] = DEFAULT_QPS
    """Feature-video QPs, one Representation each."""
    preset: str = "medium"
    """x265 preset."""
    codec: str = "hevc"
    """Feature-video codec (only HEVC so far)."""
    jobs: int = field(default_factory=lambda: os.cpu_count() or 1)
    """Encodes run in parallel."""
    plas: PLASConfig = field(default_factory=PLASConfig)
    """PLAS sort settings."""
    sort: bool = True
    """PLAS-sort the Gaussians (False: keep the model's order, for comparisons)."""
    stats_views: int = 4
    """Cameras per GOP for the rendered-view PSNR."""
    stats_frames: int = 3
    """Frames per GOP for the rendered-view PSNR."""
    resume: bool = False
    """Skip (GOP, QP) tasks whose outputs a previous interrupted run left complete."""

    def validate(self) -> None:
        if not self.qps or any(not 0 <= q <= 51 for q in self.qps) or len(set(self.qps)) != len(self.qps):
            raise FieldError("qps", f"must list distinct QPs in 0..51, got {self.qps}")
        if self.preset not in PRESETS:
            raise FieldError("preset", f"must be one of {', '.join(PRESETS)}, got {self.preset!r}")
        if self.codec != "hevc":
            raise FieldError("codec", f"{self.codec!r} is not supported (hevc only so far)")
        if self.jobs < 1:
            raise FieldError("jobs", f"must be >= 1, got {self.jobs}")

    def digest_fields(self) -> dict:
        """What determines the output bytes (not jobs or resume)."""
        return {"qps": list(self.qps), "preset": self.preset, "codec": self.codec,
                "plas": asdict(self.plas), "sort": self.sort, "stats_views": self.stats_views,
                "stats_frames": self.stats_frames, "format": 1}


@dataclass
class GOPResult:
    keyframe_bytes: int = 0
    representations: dict[str, dict] = field(default_factory=dict)


def pack_id(model_dir: Path, cfg: PackConfig) -> str:
    digest = hashlib.sha256((Path(model_dir) / MODEL_META).read_bytes())
    digest.update(json.dumps(cfg.digest_fields(), sort_keys=True).encode())
    return digest.hexdigest()[:12]


class PackState:
    """Hashes of finished outputs, saved after every task (for --resume)."""

    def __init__(self, out: Path, ident: str, resume: bool):
        self.path = out / PACK_STATE
        self.lock = threading.Lock()
        self.doc = {"pack_id": ident, "files": {}, "tasks": {}}
        if resume and self.path.is_file():
            try:
                old = json.loads(self.path.read_text())
            except json.JSONDecodeError:
                old = {}
            if old.get("pack_id") == ident:
                self.doc = old

    def done(self, out: Path, task: str) -> dict | None:
        """The recorded result of `task` if every file it wrote is still intact."""
        entry = self.doc["tasks"].get(task)
        if entry is None:
            return None
        for rel in entry["files"]:
            path = out / rel
            if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != self.doc["files"].get(rel):
                return None
        return entry["result"]

    def record(self, task: str, files: dict[str, bytes], result: dict) -> None:
        with self.lock:
            for rel, data in files.items():
                self.doc["files"][rel] = hashlib.sha256(data).hexdigest()
            self.doc["tasks"][task] = {"files": sorted(files), "result": result}
            atomic_write_bytes(self.path, json.dumps(self.doc, indent=1, sort_keys=True).encode())


def check_output_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise StgsError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not ((out / PACK_STATE).exists() or (out / MANIFEST).exists()):
        raise StgsError(f"{out}: folder is not empty and not a packaged scene; refusing to write into it")


def stats_cameras(model_dir: Path, model: GOPModel, count: int) -> list[Camera]:
    """Ground-truth cameras of a synthetic scene, else an orbit around the Gaussians."""
    if (Path(model_dir) / GROUND_TRUTH_DIR / CAMERAS).is_file():
        return load_ground_truth(model_dir)[1][:count]
    return framing_orbit(model, count, 320, 240)


def mse_psnr(mse: list[float]) -> float:
    """PSNR of the mean of squared errors (99 dB when identical)."""
    m = sum(mse) / len(mse)
    return 99.0 if m == 0 else 10 * math.log10(1.0 / m)


@dataclass
class PreparedGOP:
    """Everything a GOP's QP tasks share, computed once per GOP."""

    index: int
    original: GOPModel
    """The uncompressed GOP as stored in the model dir."""
    frames: np.ndarray
    """(E, 4S, 4S) 12-bit feature frames of the sorted GOP."""
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


class Packer:
    """One pack run (see the module docstring)."""

    def __init__(self, model_dir: Path, out: Path, cfg: PackConfig, progress: bool = True):
        cfg.validate()
        require_ffmpeg()
        self.model_dir, self.out, self.cfg, self.progress = Path(model_dir), Path(out), cfg, progress
        self.meta: SceneMeta = read_meta(self.model_dir)
        self.side = self.meta.shape.grid_side
        if self.side == 0:
            raise StgsError(f"{model_dir}: capacity {self.meta.shape.capacity} is not a square; "
                            "the packager needs N = S² Gaussians")
        check_output_dir(self.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.id = pack_id(self.model_dir, cfg)
        self.version_dir = version_dir(self.id)
        self.timing = VideoTiming.for_gop(self.meta.shape.num_features, self.meta.shape.gop_size,
                                          self.meta.fps)
        self.state = PackState(self.out, self.id, cfg.resume)
        self.init_segments: dict[int, bytes] = {}
        self.lock = threading.Lock()

    def keyframe_path(self, k: int) -> str:
        return keyframe_path(self.version_dir, k)

    def feature_path(self, qp: int, k: int | None) -> str:
        return feature_path(self.version_dir, rep_id(qp), k)

    def write(self, rel: str, data: bytes) -> None:
        atomic_write_bytes(self.out / rel, data)

    def prepare_gop(self, k: int) -> PreparedGOP:
        """Sort, tile, write nothing yet: GOP k's keyframe, feature frames and reference views."""
        original = load_gop(self.model_dir, self.meta, k)
        if self.cfg.sort:
            cfg = PLASConfig(**{**asdict(self.cfg.plas), "seed": self.cfg.plas.seed + k})
            order = plas_order(sort_key(original, cfg), self.side, cfg)
            model = permute_gop(original, order)
        else:
            model = original
        feats = model.features.detach()
        ranges = feature_ranges(feats)
        frames = tile_frames(quantize_features(feats, ranges), self.side).numpy().astype(np.uint16)
        keyframe = encode_keyframe(k, model, ranges)
        cams = stats_cameras(self.model_dir, original, self.cfg.stats_views)
        g = self.meta.shape.gop_size
        views = [(f, cam) for f in sorted({0, g // 2, g - 1})[: self.cfg.stats_frames] for cam in cams]
        renderer = FrameRenderer(original)
        reference = [renderer.render(f, cam).clamp(0, 1) for f, cam in views]
        decoded = decode_keyframe(keyframe, self.meta.shape, k, max_bytes=len(keyframe))
        return PreparedGOP(k, original, frames, ranges, keyframe, decoded, views, reference)

    def encode_task(self, k: int, qp: int, frames: np.ndarray) -> tuple[bytes, bytes]:
        init, media = split_fragmented(encode_gop(frames, qp, self.timing, self.cfg.preset))
        media = set_timeline(media, k + 1, k * self.timing.segment_ticks(self.meta.shape.num_features))
        with self.lock:
            first = self.init_segments.setdefault(qp, init)
        if first != init:
            raise RuntimeError(f"GOP {k} at QP {qp} produced a different init segment; "
                               "Representations need one init segment for all GOPs")
        return init, media

    def measure(self, gop: PreparedGOP, init: bytes, media: bytes) -> dict:
        """Bytes, decoded-feature PSNR and rendered-view PSNR of one media segment."""
        shape = self.meta.shape
        h = w = 4 * self.side
        decoded_frames = decode_segment(init, media, shape.num_features, h, w)
        feature_psnr = psnr(torch.from_numpy(decoded_frames.astype(np.float32)) / VIDEO_MAX,
                            torch.from_numpy(gop.frames.astype(np.float32)) / VIDEO_MAX)
        features = features_from_frames(decoded_frames, self.side, gop.ranges)
        renderer = FrameRenderer(gop.decoded_keyframe.to_model(features))
        mse = [(renderer.render(f, cam).clamp(0, 1).double() - ref.double()).square().mean().item()
               for (f, cam), ref in zip(gop.views, gop.reference, strict=True)]
        return {"bytes": len(media), "feature_psnr": round(min(feature_psnr, 99.0), 4),
                "render_psnr": round(mse_psnr(mse), 4)}

    def run(self) -> dict:
        cfg = self.cfg
        results = [GOPResult() for _ in range(self.meta.num_gops)]
        total = self.meta.num_gops * len(cfg.qps)
        bar = tqdm(total=total, desc="pack GOPs x QPs", unit="seg", disable=not self.progress)

        def qp_job(gop: PreparedGOP, qp: int) -> None:
            k = gop.index
            task = f"gop{k}-qp{qp}"
            done = self.state.done(self.out, task)
            if done is None:
                init, media = self.encode_task(k, qp, gop.frames)
                files = {self.feature_path(qp, k): media, self.feature_path(qp, None): init}
                for rel, data in files.items():
                    self.write(rel, data)
                done = self.measure(gop, init, media)
                self.state.record(task, files, done)
            results[k].representations[rep_id(qp)] = done
            bar.update(1)

        # GOP k+1 is sorted and tiled while GOP k's QPs encode; at most two GOPs are held in memory.
        with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
            previous: list = []
            for k in range(self.meta.num_gops):
                gop = self.prepare_gop(k)
                self.write(self.keyframe_path(k), gop.keyframe)
                results[k].keyframe_bytes = len(gop.keyframe)
                current = [pool.submit(qp_job, gop, qp) for qp in cfg.qps]
                for future in previous:
                    future.result()
                previous = current
            for future in previous:
                future.result()
        bar.close()
        codecs = {qp: hevc_codecs((self.out / self.feature_path(qp, None)).read_bytes()) for qp in cfg.qps}
        stats = self.stats_doc(results)
        atomic_write_bytes(self.out / STATS, (json.dumps(stats, indent=2) + "\n").encode())
        self.write_cameras()
        atomic_write_bytes(self.out / MANIFEST, self.manifest(results, codecs).to_xml())
        return stats

    def write_cameras(self) -> None:
        """The scene's cameras beside the MPD (players offer them as viewpoints), when the model dir has them:
        its cameras.json (stgs train) or its ground-truth cameras (stgs synth)."""
        if (self.model_dir / CAMERAS).is_file():
            data = (self.model_dir / CAMERAS).read_bytes()
        elif (self.model_dir / GROUND_TRUTH_DIR / CAMERAS).is_file():
            cameras = load_ground_truth(self.model_dir)[1]
            doc = {"format": CAMERAS_FORMAT, "version": 1, "cameras": [c.to_json() for c in cameras]}
            data = (json.dumps(doc, indent=1) + "\n").encode()
        else:
            return
        atomic_write_bytes(self.out / CAMERAS, data)

    def seconds_per_gop(self) -> float:
        return self.meta.shape.gop_size / self.meta.fps

    def bandwidth(self, sizes: list[int]) -> int:
        """@bandwidth: the bit rate that delivers the largest segment within one segment duration."""
        return math.ceil(max(sizes) * 8 / self.seconds_per_gop())

    def manifest(self, results: list[GOPResult], codecs: dict[int, str]) -> MPD:
        shape, timing = self.meta.shape, self.timing
        seg_ticks = timing.segment_ticks(shape.num_features)
        params = (f"version=1;capacity={shape.capacity};grid_side={self.side};gop_size={shape.gop_size};"
                  f"window={shape.window};pe_freqs={shape.pe_freqs};fps={self.meta.fps:g}")
        keyframes = AdaptationSet(
            1, "application", KEYFRAME_MIME_TYPE,
            SegmentTemplate(keyframe_template(self.version_dir), timing.timescale, seg_ticks, 0),
            [Representation(KEYFRAME_REP, self.bandwidth([r.keyframe_bytes for r in results]))],
            [Descriptor(KEYFRAME_SCHEME, params)])
        rate = timing.rate
        frame_rate = str(rate.numerator) if rate.denominator == 1 else f"{rate.numerator}/{rate.denominator}"
        reps = [Representation(rep_id(qp), self.bandwidth([r.representations[rep_id(qp)]["bytes"] for r in results]),
                               codecs[qp], 4 * self.side, 4 * self.side, frame_rate, [KEYFRAME_REP], ["cdsc"])
                for qp in sorted(self.cfg.qps)]
        features = AdaptationSet(
            2, "video", "video/mp4",
            SegmentTemplate(feature_media_template(self.version_dir), timing.timescale, seg_ticks, 0,
                            feature_init_template(self.version_dir)),
            reps, [Descriptor(FEATURE_SCHEME, "tiles=4x4;channels=16;bits=12")])
        duration = self.meta.num_gops * self.seconds_per_gop()
        return MPD(duration, self.seconds_per_gop(), [Period("0", [keyframes, features])])

    def stats_doc(self, results: list[GOPResult]) -> dict:
        reps = {}
        for qp in sorted(self.cfg.qps):
            rows = [r.representations[rep_id(qp)] for r in results]
            reps[rep_id(qp)] = {
                "qp": qp, "bandwidth": self.bandwidth([row["bytes"] for row in rows]),
                "mean_bytes": sum(row["bytes"] for row in rows) / len(rows),
                "mean_feature_psnr": sum(row["feature_psnr"] for row in rows) / len(rows),
                "mean_render_psnr": sum(row["render_psnr"] for row in rows) / len(rows)}
        return {"format": "streamstgs-stats", "version": 1, "pack_id": self.id,
                "segment_seconds": self.seconds_per_gop(), "frames_per_gop": self.meta.shape.gop_size,
                "keyframe_bandwidth": self.bandwidth([r.keyframe_bytes for r in results]),
                "representations": reps,
                "gops": [{"index": k, "keyframe_bytes": r.keyframe_bytes,
                          "representations": {rep_id(qp): r.representations[rep_id(qp)] for qp in sorted(self.cfg.qps)}}
                         for k, r in enumerate(results)]}


def pack(model_dir: Path, out: Path, cfg: PackConfig | None = None, progress: bool = True) -> dict:
    """Package a model dir into a DASH tree at `out`; returns the stats document."""
    return Packer(model_dir, Path(out), cfg or PackConfig(), progress).run()
