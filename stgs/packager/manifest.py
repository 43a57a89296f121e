"""The manifest layer of the packager: segment records in, `@bandwidth`, the MPD and stats.json out.

As a muxer reports each finished segment to a notifier (shaka-packager), the
packer reports a `SegmentRecord` (number, duration, bytes, quality) per
segment to a `ManifestBuilder`; each Representation accumulates its records,
its `@bandwidth` comes from them (the rate that delivers the largest segment
within its duration), and the MPD and the statistics are written from them
alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction

from stgs.codec.video import CODECS
from stgs.model.gop import GOPShape
from stgs.mpd.model import MPD, AdaptationSet, Descriptor, Period, Representation, SegmentTemplate
from stgs.mpd.profile import (
    FEATURE_SCHEME,
    KEYFRAME_QUANT_SCHEME,
    KEYFRAME_SCHEME,
    QUALITY_SCHEME,
    STATIC_SCHEME,
    FeatureDescriptor,
    KeyframeDescriptor,
    QualityDescriptor,
    StaticLayerDescriptor,
)
from stgs.tree import (
    KEYFRAME_MIME_TYPE,
    KEYFRAME_REP,
    STATIC_MIME_TYPE,
    STATIC_REP,
    feature_init_template,
    feature_media_template,
    keyframe_template,
    packaged_rep_id,
    paired_keyframe_bytes,
    quality_measure,
    static_template,
)

FEATURE_SETS = {"hevc": 2, "av1": 3}
"""Each codec's feature AdaptationSet @id, HEVC first. With both, they share @group FEATURE_GROUP."""
FEATURE_GROUP = 2

STATS_FORMAT = "streamstgs-stats"

STILL_SECONDS = 1
"""A still scene's nominal Period (seconds): DASH needs a positive duration; a still has no timeline."""


@dataclass(frozen=True)
class SegmentRecord:
    """One finished segment, as the packer reports it."""

    number: int
    """$Number$: the GOP index."""
    duration_s: float
    bytes: int
    quality: dict = field(default_factory=dict)
    """Measures of a feature segment (feature_psnr, render_psnr and, where known, truth_psnr); empty for keyframes."""


@dataclass
class RepresentationRecords:
    """The segments of one Representation, in any order of arrival."""

    rep_id: str
    segments: dict[int, SegmentRecord] = field(default_factory=dict)

    def add(self, record: SegmentRecord) -> None:
        self.segments[record.number] = record

    def bandwidth(self) -> int:
        """@bandwidth (bit/s): the rate that delivers the largest segment within its duration."""
        return math.ceil(max(r.bytes * 8 / r.duration_s for r in self.segments.values()))

    def ordered(self) -> list[SegmentRecord]:
        return [self.segments[k] for k in sorted(self.segments)]

    def mean(self, measure: str) -> float:
        """The mean of a feature segment measure (feature_psnr, render_psnr, truth_psnr) over the GOPs."""
        return sum(s.quality[measure] for s in self.segments.values()) / len(self.segments)

    def has(self, measure: str) -> bool:
        return all(measure in s.quality for s in self.segments.values())

    def quality(self) -> float:
        """The mean of what the rung's quality is judged by (stgs.tree.quality_measure over its GOPs)."""
        return self.mean(quality_measure([s.quality for s in self.segments.values()]))

    def descriptor(self) -> QualityDescriptor:
        return QualityDescriptor(self.mean("render_psnr"),
                                 self.mean("truth_psnr") if self.has("truth_psnr") else None)


@dataclass(frozen=True)
class StaticRecord:
    """The static-layer segment of a format-2 pack, as the packer reports it."""

    bytes: int
    descriptor: StaticLayerDescriptor


@dataclass
class ManifestBuilder:
    """Collects segment records per Representation and builds the MPD and stats.json from them."""

    shape: GOPShape
    grid_side: int
    fps: float
    version: str
    """The folder all segments of this pack live under (stgs.tree.version_dir)."""
    timescale: int
    segment_ticks: int
    frame_rate: Fraction
    """The feature video's frame rate."""
    keyframe_reps: dict[str, RepresentationRecords] = field(
        default_factory=lambda: {KEYFRAME_REP: RepresentationRecords(KEYFRAME_REP)})
    """Keyframe Representations: the lossless one, then any lossy keyframe rungs."""
    keyframe_quants: dict[str, str] = field(default_factory=dict)
    """A lossy keyframe Representation's quantisation (stgs.codec.quant.KeyframeQuant.value)."""
    pairing: dict[str, str] = field(default_factory=dict)
    """Feature Representation -> the keyframe Representation it plays with (absent: the lossless one)."""
    features: dict[str, RepresentationRecords] = field(default_factory=dict)
    codecs: dict[str, str] = field(default_factory=dict)
    """@codecs per feature Representation."""
    static: StaticRecord | None = None
    """The static layer's segment (format 2), or None (format 1: no static AdaptationSet)."""

    @property
    def segment_seconds(self) -> float:
        return self.shape.gop_size / self.fps

    @property
    def keyframes(self) -> RepresentationRecords:
        """The lossless keyframe Representation's segments."""
        return self.keyframe_reps[KEYFRAME_REP]

    def on_keyframe(self, record: SegmentRecord, rep: str = KEYFRAME_REP, quant: str | None = None) -> None:
        """A keyframe segment of Representation `rep` (a lossy rung's with its `quant`)."""
        self.keyframe_reps.setdefault(rep, RepresentationRecords(rep)).add(record)
        if quant is not None:
            self.keyframe_quants[rep] = quant

    def keyframe_order(self) -> list[str]:
        """Keyframe Representation ids, lossless first, then the lossy ones by falling bandwidth."""
        lossy = sorted((r for r in self.keyframe_reps if r != KEYFRAME_REP),
                       key=lambda r: (-self.keyframe_reps[r].bandwidth(), r))
        return [KEYFRAME_REP, *lossy]

    def on_static(self, record: StaticRecord) -> None:
        self.static = record

    def on_feature_segment(self, rep_id: str, record: SegmentRecord) -> None:
        self.features.setdefault(rep_id, RepresentationRecords(rep_id)).add(record)

    def ladder(self, codec: str | None = None) -> list[RepresentationRecords]:
        """Feature Representations of `codec` (None: every codec, HEVC first), each codec's in ascending ladder
        point (the packager names them `qp<N>`, `av1q<N>`)."""
        order = list(FEATURE_SETS)
        reps = [r for r in self.features.values() if codec is None or packaged_rep_id(r.rep_id)[0] == codec]
        return sorted(reps, key=lambda r: (order.index(packaged_rep_id(r.rep_id)[0]), packaged_rep_id(r.rep_id)[1]))

    def codec_names(self) -> list[str]:
        """The codecs of the feature Representations reported, HEVC first."""
        present = {packaged_rep_id(r)[0] for r in self.features}
        return [c for c in FEATURE_SETS if c in present]

    def mpd(self) -> MPD:
        if self.still:
            return self.still_mpd()
        shape, side = self.shape, self.grid_side
        descriptor = KeyframeDescriptor(shape.capacity, shape.gop_size, shape.window, shape.pe_freqs, self.fps)
        keyframes = AdaptationSet(
            1, "application", KEYFRAME_MIME_TYPE,
            SegmentTemplate(keyframe_template(self.version), self.timescale, self.segment_ticks, 0),
            [Representation(r, self.keyframe_reps[r].bandwidth(),
                             supplemental=[Descriptor(KEYFRAME_QUANT_SCHEME, self.keyframe_quants[r])]
                             if r in self.keyframe_quants else [])
             for r in self.keyframe_order()],
            [Descriptor(KEYFRAME_SCHEME, descriptor.value)])
        rate = self.frame_rate
        frame_rate = str(rate.numerator) if rate.denominator == 1 else f"{rate.numerator}/{rate.denominator}"
        codecs = self.codec_names()
        features = []
        for codec in codecs:
            set_id, bits = FEATURE_SETS[codec], CODECS[codec].bits
            ladder = self.ladder(codec)
            best_first = sorted(ladder, key=lambda r: (-r.quality(), -r.mean("render_psnr")))
            reps = [Representation(r.rep_id, r.bandwidth(), self.codecs[r.rep_id], 4 * side, 4 * side, frame_rate,
                                   [self.pairing.get(r.rep_id, KEYFRAME_REP)], ["cdsc"], best_first.index(r) + 1,
                                   [Descriptor(QUALITY_SCHEME, r.descriptor().value)])
                    for r in ladder]
            features.append(AdaptationSet(
                set_id, "video", "video/mp4",
                SegmentTemplate(feature_media_template(self.version), self.timescale, self.segment_ticks, 0,
                                feature_init_template(self.version)),
                reps, [Descriptor(FEATURE_SCHEME, FeatureDescriptor(bits).value)],
                group=FEATURE_GROUP if len(codecs) > 1 else None))
        gops = len(self.keyframes.segments)
        sets = [keyframes, *features] if self.static is None else [
            self.static_set(self.timescale, gops * self.segment_ticks, gops * self.segment_seconds), keyframes,
            *features]
        return MPD(gops * self.segment_seconds, self.segment_seconds, [Period("0", sets)])

    @property
    def still(self) -> bool:
        """A still scene: a static layer was reported and no GOP."""
        return self.static is not None and not self.keyframes.segments

    def still_mpd(self) -> MPD:
        """A still scene's MPD: the static-layer AdaptationSet alone, in a Period of STILL_SECONDS
        (manifests/PROFILE.md, "A still scene")."""
        return MPD(STILL_SECONDS, STILL_SECONDS, [Period("0", [self.static_set(1, STILL_SECONDS, STILL_SECONDS)])])

    def static_set(self, timescale: int, ticks: int, seconds: float) -> AdaptationSet:
        """The static layer's AdaptationSet: one segment spanning the Period, `ticks` in `timescale` (`seconds`)
        (manifests/PROFILE.md)."""
        if self.static is None:
            raise ValueError("no static layer segment was reported")
        bandwidth = math.ceil(self.static.bytes * 8 / seconds)
        return AdaptationSet(
            0, "application", STATIC_MIME_TYPE, SegmentTemplate(static_template(self.version), timescale, ticks, 0),
            [Representation(STATIC_REP, bandwidth)], [Descriptor(STATIC_SCHEME, self.static.descriptor.value)])

    def static_stats(self) -> dict:
        """stats.json's `static`: the static layer's segment bytes and sizes."""
        if self.static is None:
            raise ValueError("no static layer segment was reported")
        d = self.static.descriptor
        return {"bytes": self.static.bytes, "capacity": d.capacity, "grid_side": d.grid_side, "sh_degree": d.sh_degree}

    def still_stats(self, pack_id: str) -> dict:
        """A still scene's stats.json: the static layer's segment, no Representation or GOP (manifests/PROFILE.md)."""
        return {"format": STATS_FORMAT, "version": 1, "pack_id": pack_id, "still": True, "representations": {},
                "gops": [], "static": self.static_stats()}

    def stats(self, pack_id: str) -> dict:
        """stats.json: per Representation and per GOP, bytes and quality (manifests/PROFILE.md)."""
        if self.still:
            return self.still_stats(pack_id)
        reps = {}
        lossy = [r for r in self.keyframe_order() if r != KEYFRAME_REP]
        for r in self.ladder():
            rows = r.ordered()
            codec, point = packaged_rep_id(r.rep_id)
            reps[r.rep_id] = {
                "codec": codec, "bits": CODECS[codec].bits, "qp": point, "bandwidth": r.bandwidth(),
                "mean_bytes": sum(s.bytes for s in rows) / len(rows),
                "mean_feature_psnr": r.mean("feature_psnr"), "mean_render_psnr": r.mean("render_psnr")}
            if r.has("truth_psnr"):
                reps[r.rep_id]["mean_truth_psnr"] = r.mean("truth_psnr")
            if lossy:
                reps[r.rep_id]["keyframes"] = self.pairing.get(r.rep_id, KEYFRAME_REP)
        doc = {"format": STATS_FORMAT, "version": 1, "pack_id": pack_id,
               "segment_seconds": self.segment_seconds, "frames_per_gop": self.shape.gop_size,
               "keyframe_bandwidth": self.keyframes.bandwidth(),
               "representations": reps,
               "gops": [{"index": kf.number, "keyframe_bytes": kf.bytes,
                         "representations": {r.rep_id: {"bytes": r.segments[kf.number].bytes,
                                                        **r.segments[kf.number].quality} for r in self.ladder()}}
                        | ({"keyframes": {rep: self.keyframe_reps[rep].segments[kf.number].bytes for rep in lossy}}
                           if lossy else {})
                        for kf in self.keyframes.ordered()]}
        if lossy:
            doc["keyframe_representations"] = {
                rep: {"quant": self.keyframe_quants[rep], "bandwidth": self.keyframe_reps[rep].bandwidth()}
                for rep in lossy}
        if self.static is not None:  # format 2 only: a format-1 tree's stats.json is unchanged
            doc["static"] = self.static_stats()
        return doc


def kb_per_frame(stats: dict, rep_id: str, static_frames: int | None = None) -> float:
    """KB per frame of a stats.json's feature Representation `rep_id`: keyframes and features over the scene's
    frames, plus a format-2 tree's static layer amortised over `static_frames` (default: the scene's frames)."""
    gops = stats["gops"]
    frames = len(gops) * stats["frames_per_gop"]
    paired = stats["representations"][rep_id].get("keyframes", KEYFRAME_REP)
    content = sum(paired_keyframe_bytes(g, paired) + g["representations"][rep_id]["bytes"] for g in gops)
    static = stats["static"]["bytes"] if "static" in stats else 0
    return (content / frames + static / (static_frames or frames)) / 1e3
