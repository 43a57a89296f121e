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

from stgs.model.gop import GOPShape
from stgs.mpd import MPD, AdaptationSet, Descriptor, Period, Representation, SegmentTemplate
from stgs.mpd_profile import FEATURE_SCHEME, KEYFRAME_SCHEME, STATIC_SCHEME, KeyframeDescriptor, StaticLayerDescriptor
from stgs.tree import (
    KEYFRAME_MIME_TYPE,
    KEYFRAME_REP,
    STATIC_MIME_TYPE,
    STATIC_REP,
    feature_init_template,
    feature_media_template,
    keyframe_template,
    qp_of,
    static_template,
)

STATS_FORMAT = "streamstgs-stats"


@dataclass(frozen=True)
class SegmentRecord:
    """One finished segment, as the packer reports it."""

    number: int
    """$Number$: the GOP index."""
    duration_s: float
    bytes: int
    quality: dict = field(default_factory=dict)
    """Measures of a feature segment (feature_psnr, render_psnr); empty for keyframes."""


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
    keyframes: RepresentationRecords = field(default_factory=lambda: RepresentationRecords(KEYFRAME_REP))
    features: dict[str, RepresentationRecords] = field(default_factory=dict)
    codecs: dict[str, str] = field(default_factory=dict)
    """@codecs per feature Representation."""
    static: StaticRecord | None = None
    """The static layer's segment (format 2), or None (format 1: no static AdaptationSet)."""

    @property
    def segment_seconds(self) -> float:
        return self.shape.gop_size / self.fps

    def on_keyframe(self, record: SegmentRecord) -> None:
        self.keyframes.add(record)

    def on_static(self, record: StaticRecord) -> None:
        self.static = record

    def on_feature_segment(self, rep_id: str, record: SegmentRecord) -> None:
        self.features.setdefault(rep_id, RepresentationRecords(rep_id)).add(record)

    def ladder(self) -> list[RepresentationRecords]:
        """Feature Representations in ascending QP (the packager names each `qp<N>`)."""
        return sorted(self.features.values(), key=lambda r: qp_of(r.rep_id))

    def mpd(self) -> MPD:
        shape, side = self.shape, self.grid_side
        descriptor = KeyframeDescriptor(shape.capacity, shape.gop_size, shape.window, shape.pe_freqs, self.fps)
        keyframes = AdaptationSet(
            1, "application", KEYFRAME_MIME_TYPE,
            SegmentTemplate(keyframe_template(self.version), self.timescale, self.segment_ticks, 0),
            [Representation(KEYFRAME_REP, self.keyframes.bandwidth())],
            [Descriptor(KEYFRAME_SCHEME, descriptor.value)])
        rate = self.frame_rate
        frame_rate = str(rate.numerator) if rate.denominator == 1 else f"{rate.numerator}/{rate.denominator}"
        reps = [Representation(r.rep_id, r.bandwidth(), self.codecs[r.rep_id], 4 * side, 4 * side, frame_rate,
                               [KEYFRAME_REP], ["cdsc"]) for r in self.ladder()]
        features = AdaptationSet(
            2, "video", "video/mp4",
            SegmentTemplate(feature_media_template(self.version), self.timescale, self.segment_ticks, 0,
                            feature_init_template(self.version)),
            reps, [Descriptor(FEATURE_SCHEME, "tiles=4x4;channels=16;bits=12")])
        gops = len(self.keyframes.segments)
        sets = [keyframes, features] if self.static is None else [self.static_set(gops), keyframes, features]
        return MPD(gops * self.segment_seconds, self.segment_seconds, [Period("0", sets)])

    def static_set(self, gops: int) -> AdaptationSet:
        """The static layer's AdaptationSet: one segment spanning the Period (manifests/PROFILE.md)."""
        bandwidth = math.ceil(self.static.bytes * 8 / (gops * self.segment_seconds))
        return AdaptationSet(
            0, "application", STATIC_MIME_TYPE,
            SegmentTemplate(static_template(self.version), self.timescale, gops * self.segment_ticks, 0),
            [Representation(STATIC_REP, bandwidth)], [Descriptor(STATIC_SCHEME, self.static.descriptor.value)])

    def stats(self, pack_id: str) -> dict:
        """stats.json: per Representation and per GOP, bytes and quality (manifests/PROFILE.md)."""
        reps = {}
        for r in self.ladder():
            rows = r.ordered()
            reps[r.rep_id] = {
                "qp": qp_of(r.rep_id), "bandwidth": r.bandwidth(),
                "mean_bytes": sum(s.bytes for s in rows) / len(rows),
                "mean_feature_psnr": sum(s.quality["feature_psnr"] for s in rows) / len(rows),
                "mean_render_psnr": sum(s.quality["render_psnr"] for s in rows) / len(rows)}
        doc = {"format": STATS_FORMAT, "version": 1, "pack_id": pack_id,
               "segment_seconds": self.segment_seconds, "frames_per_gop": self.shape.gop_size,
               "keyframe_bandwidth": self.keyframes.bandwidth(),
               "representations": reps,
               "gops": [{"index": kf.number, "keyframe_bytes": kf.bytes,
                         "representations": {r.rep_id: {"bytes": r.segments[kf.number].bytes,
                                                        **r.segments[kf.number].quality} for r in self.ladder()}}
                        for kf in self.keyframes.ordered()]}
        if self.static is not None:  # format 2 only: a format-1 tree's stats.json is unchanged
            d = self.static.descriptor
            doc["static"] = {"bytes": self.static.bytes, "capacity": d.capacity, "grid_side": d.grid_side,
                             "sh_degree": d.sh_degree}
        return doc


def kb_per_frame(stats: dict, rep_id: str, static_frames: int | None = None) -> float:
    """KB per frame of a stats.json's feature Representation `rep_id`: keyframes and features over the scene's
    frames, plus a format-2 tree's static layer amortised over `static_frames` (default: the scene's frames)."""
    gops = stats["gops"]
    frames = len(gops) * stats["frames_per_gop"]
    content = sum(g["keyframe_bytes"] + g["representations"][rep_id]["bytes"] for g in gops)
    static = stats["static"]["bytes"] if "static" in stats else 0
    return (content / frames + static / (static_frames or frames)) / 1e3
