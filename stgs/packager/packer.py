"""`stgs pack MODEL_DIR OUT_DIR`: a model dir -> a DASH tree (manifests/PROFILE.md).

Per GOP: PLAS-sort the Gaussians, write the keyframe segment (attribute
images, weights, ranges), tile the features into frames of 12-bit (HEVC) and
10-bit (AV1) codes; per GOP and ladder point of each codec: encode the feature
video, cut it into init + media segment and place the segment on the
Representation's timeline; then measure every segment (bytes, decoded-feature
PSNR, rendered-view PSNR against the uncompressed model at the scene's cameras),
keep the rungs of each codec (all of a fixed ladder; for an auto ladder, those
stgs.packager.ladder picks from the candidates measured) and write stats.json
and, last, manifest.mpd.

All segment files live under a folder named after a digest of the inputs and
settings (`v-<id>/`), so a re-pack of the same inputs writes the same bytes
under the same names and a re-pack of different inputs writes new names:
content under a URL never changes.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, replace
from functools import cached_property
from pathlib import Path

from tqdm import tqdm

from stgs.camera import Camera
from stgs.codec.static import decode_static, pack_static
from stgs.codec.video import CODECS, HEVC, FeatureCodec, VideoTiming
from stgs.errors import StgsError
from stgs.fsio import atomic_write_bytes
from stgs.limits import MAX_TITLE_CHARS
from stgs.metrics import psnr
from stgs.model.renderer import render_still
from stgs.model.static import StaticLayer
from stgs.model.store import SceneMeta, load_gop, load_static, read_meta
from stgs.mpd.profile import StaticLayerDescriptor
from stgs.packager.config import PackConfig
from stgs.packager.ladder import Candidate, Verdict, allocation_saving, choose_rungs
from stgs.packager.manifest import ManifestBuilder, RepresentationRecords, SegmentRecord, StaticRecord
from stgs.packager.poster import encode_poster, render_poster, scene_document
from stgs.packager.segments import FeatureEncoder, PreparedGOP, lossy_rungs, measure, prepare_gop, quality_views
from stgs.packager.state import PackState, check_output_dir, pack_id
from stgs.synth import load_ground_truth
from stgs.tree import (
    CAMERAS,
    CAMERAS_FORMAT,
    GROUND_TRUTH_DIR,
    KEYFRAME_REP,
    MANIFEST,
    SCENE,
    STATS,
    feature_path,
    keyframe_path,
    poster_path,
    quality_measure,
    static_path,
    version_dir,
)

SEGMENT_MEASURES = ("feature_psnr", "render_psnr", "truth_psnr")
"""What a feature segment's measurement records beside its bytes (stgs.packager.segments.quality)."""


class Packer:
    """One pack run (see the module docstring): prepares GOP after GOP, encodes and measures each ladder point of
    each codec on a pool, reports every finished segment to the manifest builder, and writes stats.json and,
    last, the MPD."""

    def __init__(self, model_dir: Path, out: Path, cfg: PackConfig, progress: bool = True):
        cfg.validate()
        self.model_dir, self.out, self.cfg, self.progress = Path(model_dir), Path(out), cfg, progress
        self.meta: SceneMeta = read_meta(self.model_dir)
        self.side = self.meta.shape.grid_side
        if self.side == 0:
            raise StgsError(f"{model_dir}: capacity {self.meta.shape.capacity} is not a square; "
                            "the packager needs N = S² Gaussians")
        self.static: StaticLayer | None = load_static(self.model_dir, self.meta)
        """The scene's static layer as trained (format 2), or None."""
        self.id = pack_id(self.model_dir, self.meta.gop_files, cfg.digest_fields())
        self.version_dir = version_dir(self.id)
        shape = self.meta.shape
        self.timing = VideoTiming.for_gop(shape.num_features, shape.gop_size, self.meta.fps)
        self.state: PackState | None = None
        self.encoder = FeatureEncoder(self.timing, shape.num_features, cfg.preset_of, cfg.loop_filters)
        self.builder = ManifestBuilder(shape, self.side, self.meta.fps, self.version_dir, self.timing.timescale,
                                       self.timing.segment_ticks(shape.num_features), self.timing.rate)

    def prepare_output(self) -> None:
        """Check the output folder and open the resume state; done once, by the run's driver (never by a task)."""
        check_output_dir(self.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.state = PackState(self.out, self.id, self.cfg.resume)

    def opened_state(self) -> PackState:
        """The resume state prepare_output opened."""
        if self.state is None:
            raise RuntimeError("the resume state is opened by prepare_output(), in the run's driver")
        return self.state

    @property
    def seconds_per_gop(self) -> float:
        return self.meta.shape.gop_size / self.meta.fps

    def prepare_gop(self, k: int) -> PreparedGOP:
        """Sort, tile, write nothing yet: GOP k's keyframe, feature frames and reference views (of the
        composite with the static layer, in a layered scene)."""
        bits = sorted({CODECS[c].bits for c in self.cfg.codecs} | {HEVC.bits})  # HEVC's: feature_psnr's reference
        return prepare_gop(self.model_dir, self.meta, k, self.cfg.plas if self.cfg.sort else None,
                           self.cfg.stats_views, self.cfg.stats_frames, self.static, tuple(bits),
                           self.cfg.lossy_keyframes())

    def write_keyframes(self, gop: PreparedGOP) -> None:
        """GOP k's keyframe segments (lossless and lossy) into the tree."""
        self.write(keyframe_path(self.version_dir, gop.index), gop.keyframe)
        for rep, (data, _) in gop.lossy.items():
            self.write(keyframe_path(self.version_dir, gop.index, rep), data)

    def report_keyframes(self, k: int, sizes: dict[str, int]) -> None:
        """Tell the builder of GOP k's keyframe segments (Representation id -> bytes)."""
        quants = lossy_rungs(self.cfg.lossy_keyframes())
        for rep, size in sizes.items():
            quant = None if rep not in quants else quants[rep].value
            self.builder.on_keyframe(SegmentRecord(k, self.seconds_per_gop, size), rep, quant)

    def write_static(self) -> None:
        """A layered scene's static layer, sorted and encoded, into the tree (before any GOP: the QP tasks
        measure the composite with the segment as a player decodes it), and its record to the builder."""
        if self.static is None:
            return
        data = pack_static(self.static, self.cfg.plas if self.cfg.sort else None)
        self.write(static_path(self.version_dir), data)
        self.builder.on_static(StaticRecord(len(data), StaticLayerDescriptor(self.static.capacity,
                                                                             self.static.sh_degree)))

    @cached_property
    def decoded_static(self) -> StaticLayer | None:
        """The static layer as a player decodes it from the tree (None in format 1)."""
        if self.static is None:
            return None
        data = (self.out / static_path(self.version_dir)).read_bytes()
        return decode_static(data, self.static.capacity, self.static.sh_degree, len(data))

    def write(self, rel: str, data: bytes) -> None:
        atomic_write_bytes(self.out / rel, data)

    def feature_task(self, gop: PreparedGOP, codec: FeatureCodec, q: int) -> SegmentRecord:
        """GOP k at one ladder point: encoded, written and measured (or, resuming, what an earlier run recorded)."""
        task = point_task_name(gop.index, codec, q)
        state = self.opened_state()
        done = state.done(self.out, task)
        if done is None:
            digests, done = self.encode_segment(gop, codec, q)
            state.record(task, digests, done)
        return self.segment_record(gop.index, done)

    def encode_segment(self, gop: PreparedGOP, codec: FeatureCodec, q: int) -> tuple[dict[str, str], dict]:
        """GOP k's feature video at one ladder point encoded, its init and media segments written, the media
        measured: (the SHA-256 of each file by path, the measurements)."""
        k, rep = gop.index, codec.rep_id(q)
        init, media = self.encoder.encode(k, codec, q, gop.frames[codec.bits])
        files = {feature_path(self.version_dir, rep, k): media, feature_path(self.version_dir, rep, None): init}
        for rel, data in files.items():
            self.write(rel, data)
        digests = {rel: hashlib.sha256(data).hexdigest() for rel, data in files.items()}
        return digests, measure(gop, codec, init, media, self.meta, self.decoded_static)

    def segment_record(self, k: int, done: dict) -> SegmentRecord:
        return SegmentRecord(k, self.seconds_per_gop, done["bytes"], {key: value for key, value in done.items()
                                                                      if key in (*SEGMENT_MEASURES, "keyframes")})

    def run(self) -> dict:
        cfg = self.cfg
        ladder = cfg.encodes()
        bar = tqdm(total=self.meta.num_gops * len(ladder), desc="pack GOPs x ladder points", unit="seg",
                   disable=not self.progress)

        def point_job(gop: PreparedGOP, codec: FeatureCodec, q: int) -> None:
            self.builder.on_feature_segment(codec.rep_id(q), self.feature_task(gop, codec, q))
            bar.update(1)

        self.write_static()
        if self.meta.still:
            return self.finish()
        # GOP k+1 is sorted and tiled while GOP k's ladder encodes; at most two GOPs are held in memory.
        with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
            previous: list = []
            for k in range(self.meta.num_gops):
                gop = self.prepare_gop(k)
                self.write_keyframes(gop)
                self.report_keyframes(k, {KEYFRAME_REP: len(gop.keyframe)}
                                      | {rep: len(data) for rep, (data, _) in gop.lossy.items()})
                current = [pool.submit(point_job, gop, codec, q) for codec, q in ladder]
                for future in previous:
                    future.result()
                previous = current
            for future in previous:
                future.result()
        bar.close()
        return self.finish()

    def finish(self) -> dict:
        """stats.json, cameras.json, scene.json and, last, the MPD, from the segments the builder was told of."""
        stats = self.still_stats() if self.meta.still else self.ladder_stats()
        atomic_write_bytes(self.out / STATS, (json.dumps(stats, indent=2) + "\n").encode())
        self.write_cameras()
        self.write_scene()
        atomic_write_bytes(self.out / MANIFEST, self.builder.mpd().to_xml())
        return stats

    def ladder_stats(self) -> dict:
        """The rungs chosen (choose_ladder) and the stats document of a scene of GOPs."""
        for codec, q in self.cfg.encodes():
            init = (self.out / feature_path(self.version_dir, codec.rep_id(q), None)).read_bytes()
            self.builder.codecs[codec.rep_id(q)] = codec.codecs(init)
        ladders = self.choose_ladder()
        views = quality_views(self.model_dir, self.meta, lambda: load_gop(self.model_dir, self.meta, 0),
                              self.cfg.stats_views, self.cfg.stats_frames)
        return self.builder.stats(self.id) | {"quality_views": views.describe(), "ladders": ladders}

    def still_stats(self) -> dict:
        """A still scene's stats document, with the static segment's render PSNR against the uncompressed layer at
        the quality views."""
        if self.static is None or self.decoded_static is None:
            raise StgsError(f"{self.model_dir}: a still scene needs its static layer")
        static, decoded = self.static, self.decoded_static
        views = quality_views(self.model_dir, self.meta, lambda: static, self.cfg.stats_views, None)
        stats = self.builder.stats(self.id)
        stats["static"]["render_psnr"] = still_psnr(static, decoded, views.cameras)
        stats["quality_views"] = views.describe()
        return stats

    def write_scene(self) -> None:
        """scene.json, the catalogue's view of the scene, and the poster it names (unless poster is off)."""
        poster, view = None, None
        if self.cfg.poster:
            rgb, view = render_poster(self.model_dir, self.meta, self.static)
            poster = poster_path(self.version_dir)
            self.write(poster, encode_poster(rgb))
        title = self.cfg.title if self.cfg.title is not None else self.model_dir.resolve().name[:MAX_TITLE_CHARS]
        atomic_write_bytes(self.out / SCENE, scene_document(title, self.cfg.description, poster, view))

    def choose_ladder(self) -> dict:
        """Each codec's rungs, each a feature Representation paired with a keyframe Representation: every point of a
        fixed ladder with the lossless keyframe; for an auto one, the (feature point, keyframe rung) pairs
        ladder.choose_rungs keeps, at most one pair per feature point and the lossless keyframe at the top (pair_rungs).
        The other candidates' segments leave the tree and the builder, and the kept rungs carry their pair's quality.
        Returns stats.json's `ladders`."""
        out: dict = {}
        builder = self.builder
        key_bytes = {rep: sum(s.bytes for s in r.segments.values()) for rep, r in builder.keyframe_reps.items()}
        cheapest = min(key_bytes.values())
        for name in self.cfg.codecs:
            reps = builder.ladder(name)
            measure = quality_measure([s.quality for r in reps for s in r.segments.values()])
            pairs = {pair_id(r.rep_id, kf): (r, kf) for r in reps for kf in key_bytes}
            scene = [Candidate(pid, sum(s.bytes for s in r.segments.values()) + key_bytes[kf] - cheapest,
                               pair_mean(r, kf, measure)) for pid, (r, kf) in pairs.items()]
            doc: dict = {"mode": self.cfg.ladder, "measure": measure}
            if self.cfg.ladder == "auto":
                verdicts = pair_rungs(choose_rungs(scene, self.cfg.rules), pairs, {c.rep_id: c.psnr for c in scene})
                kept = [c for c in scene if c.rep_id in {v.rep_id for v in verdicts if v.kept}]
                per_gop = []
                for k in sorted(builder.keyframes.segments):  # bytes as the scene's: above the GOP's cheapest keyframe
                    keys = {rep: kr.segments[k].bytes for rep, kr in builder.keyframe_reps.items()}
                    per_gop.append([Candidate(pid, r.segments[k].bytes + keys[kf] - min(keys.values()),
                                              pair_quality(r.segments[k].quality, kf)[measure])
                                    for pid, (r, kf) in pairs.items()])
                doc |= {"rules": asdict(self.cfg.rules), "per_gop_saving": round(allocation_saving(per_gop, kept), 4)}
            else:
                verdicts = [Verdict(c.rep_id, True, "a fixed rung") for c in sorted(scene, key=lambda c: c.bytes)]
            doc["candidates"] = []
            for v in verdicts:
                r, kf = pairs[v.rep_id]
                features = sum(s.bytes for s in r.segments.values())
                entry = {"representation": v.rep_id, "bytes": features, "total_bytes": features + key_bytes[kf]}
                if len(key_bytes) > 1:
                    entry = {"representation": v.rep_id, "features": r.rep_id, "keyframes": kf} | entry
                psnrs = {m: round(pair_mean(r, kf, m), 4) for m in ("render_psnr", "truth_psnr") if r.has(m)}
                doc["candidates"].append(entry | psnrs | {"kept": v.kept, "reason": v.reason})
                if v.kept:
                    builder.pairing[r.rep_id] = kf
            for r in reps:
                if r.rep_id not in builder.pairing:
                    self.drop_rung(r.rep_id)
                else:
                    kf = builder.pairing[r.rep_id]
                    r.segments = {k: replace(s, quality=pair_quality(s.quality, kf)) for k, s in r.segments.items()}
            out[name] = doc
        for rep in [r for r in builder.keyframe_reps if r != KEYFRAME_REP and r not in builder.pairing.values()]:
            builder.keyframe_reps.pop(rep)
            builder.keyframe_quants.pop(rep, None)
            shutil.rmtree((self.out / keyframe_path(self.version_dir, 0, rep)).parent, ignore_errors=True)
        for rep in [r for r, kf in builder.pairing.items() if kf == KEYFRAME_REP]:
            builder.pairing.pop(rep)
        return out

    def drop_rung(self, rep: str) -> None:
        """A candidate that is not a rung: its segments leave the tree, the resume state and the builder."""
        self.builder.features.pop(rep, None)
        self.builder.codecs.pop(rep, None)
        folder = (self.out / feature_path(self.version_dir, rep, None)).parent
        shutil.rmtree(folder, ignore_errors=True)
        if self.state is not None:
            self.state.forget(lambda task: task.endswith(f"-{rep}"))

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


def still_psnr(reference: StaticLayer, decoded: StaticLayer, cameras: list[Camera]) -> float:
    """Mean PSNR (dB) over `cameras` of a still scene's `decoded` static layer against its `reference`."""
    values = [psnr(render_still(decoded, cam).clamp(0, 1), render_still(reference, cam).clamp(0, 1))
              for cam in cameras]
    return sum(values) / len(values)


def pair_id(feature_rep: str, keyframe_rep: str) -> str:
    """A ladder candidate's id: the feature Representation's, `+<keyframe Representation>` for a lossy keyframe."""
    return feature_rep if keyframe_rep == KEYFRAME_REP else f"{feature_rep}+{keyframe_rep}"


def pair_quality(quality: dict, keyframe_rep: str) -> dict:
    """A feature segment's measures (stgs.packager.segments.quality) when it plays with keyframe Representation
    `keyframe_rep`: its feature PSNR and that pair's rendered PSNRs."""
    base = {k: v for k, v in quality.items() if k != "keyframes"}
    return base if keyframe_rep == KEYFRAME_REP else base | quality["keyframes"][keyframe_rep]


def pair_mean(records: RepresentationRecords, keyframe_rep: str, measure: str) -> float:
    """The mean over the GOPs of a feature Representation's `measure` with keyframe Representation `keyframe_rep`."""
    values = [pair_quality(s.quality, keyframe_rep)[measure] for s in records.segments.values()]
    return sum(values) / len(values)


def pair_rungs(verdicts: list[Verdict], pairs: dict, quality: dict[str, float]) -> list[Verdict]:
    """choose_rungs' verdicts over (feature, keyframe) pairs (`quality`: each pair's), made a ladder a player can
    fetch: the top rung plays with the lossless keyframe where that renders at least as well (its lossless pair takes
    its place), and a feature Representation is one rung (a lower pair of features already kept is dropped)."""
    out = {v.rep_id: v for v in verdicts}
    kept = [v.rep_id for v in verdicts if v.kept]  # choose_rungs lists the kept ones cheapest first
    if kept:
        top_features, top_kf = pairs[kept[-1]]
        lossless = pair_id(top_features.rep_id, KEYFRAME_REP)
        if top_kf != KEYFRAME_REP and quality[lossless] >= quality[kept[-1]]:
            out[kept[-1]] = Verdict(kept[-1], False, f"the top rung plays with the lossless keyframe: {lossless}")
            out[lossless] = Verdict(lossless, True, "the top: features of the top pair, with the lossless keyframe")
            kept[-1] = lossless
    used: dict[str, str] = {}
    for pid in reversed(kept):
        features = pairs[pid][0].rep_id
        if features in used:
            out[pid] = Verdict(pid, False, f"its features are a rung already, as {used[features]}")
        else:
            used[features] = pid
    return [out[v.rep_id] for v in verdicts]


def point_task_name(k: int, codec: FeatureCodec, q: int) -> str:
    """The name of GOP k's task at one ladder point (in the resume state and the task logs): `gop3-qp20`,
    `gop3-av1q30`."""
    return f"gop{k}-{codec.rep_id(q)}"
