"""A StreamSTGS presentation as the client sees it: the MPD, resolved against its URL.

Finds the keyframe and feature-video AdaptationSets by their scheme URIs
(choosing one feature set by codec where the tree offers two: stgs.mpd.profile.choose_feature_set),
reads the scene's sizes from the keyframe descriptor, checks them against the
client's caps before anything is downloaded, and turns the SegmentTemplates
into absolute URLs (BaseURL and relative templates resolve against the MPD's
URL, RFC 3986).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from urllib.parse import urljoin

from stgs.codec.mp4 import MP4Error, media_timeline, track_timescale
from stgs.codec.video import CODECS, FeatureCodec
from stgs.errors import MPDError
from stgs.limits import (
    MAX_GOPS,
    MAX_SEGMENT_BYTES,
    SEGMENT_SLACK,
)
from stgs.model.gop import GOPShape
from stgs.mpd.model import MPD, PROFILE_STGS, AdaptationSet, Representation, parse_mpd
from stgs.mpd.profile import (
    KEYFRAME_SCHEME,
    STATIC_SCHEME,
    KeyframeDescriptor,
    QualityDescriptor,
    StaticLayerDescriptor,
    choose_feature_set,
    gop_count,
    keyframe_quant,
    paired_keyframe,
    still_static_set,
)
from stgs.tree import KEYFRAME_REP, expand_template, qp_of


@dataclass(frozen=True)
class PlaybackSpan:
    """Which part of a presentation one playback covers."""

    first_gop: int
    """k0: the GOP holding the start time."""
    frames: int
    """Frames to present from k0's first frame."""
    gops: list[int]
    """GOPs the playback needs, in order."""
    buffer_s: float
    """Download buffer capacity (at least one GOP)."""


@dataclass(frozen=True)
class Rung:
    """One feature Representation of the ladder."""

    rep_id: str
    bandwidth: int
    """@bandwidth, bit/s."""
    qp: int | None
    """QP parsed from the id (`qp<N>`), if it has that form."""
    quality: QualityDescriptor | None = None
    """Its quality descriptor (mean PSNR against the uncompressed model and, where given, the capture; None in
    trees that carry none)."""
    keyframe_rep: str = KEYFRAME_REP
    """The keyframe Representation it plays with (its @associationId)."""
    keyframe_bandwidth: int = 0
    """That keyframe Representation's @bandwidth, bit/s."""

    @property
    def total_bandwidth(self) -> int:
        """Features and keyframes, bit/s: what the ladder is ordered by."""
        return self.bandwidth + self.keyframe_bandwidth


@dataclass(frozen=True)
class StaticLayerInfo:
    """A format-2 presentation's static layer: one segment for the Period (manifests/PROFILE.md)."""

    capacity: int
    sh_degree: int
    bandwidth: int
    """@bandwidth of its Representation: its bytes x 8 over the Period's duration."""
    media: str
    """The segment's URL template."""
    rep_id: str


def _static_layer(a: AdaptationSet) -> StaticLayerInfo:
    descriptor = StaticLayerDescriptor.parse(a)
    if len(a.representations) != 1:
        raise MPDError("the static-layer AdaptationSet must have exactly one Representation")
    rep = a.representations[0]
    return StaticLayerInfo(descriptor.capacity, descriptor.sh_degree, rep.bandwidth, a.segment_template.media,
                           rep.id)



def _checked_mpd(mpd: MPD) -> MPD:
    """`mpd`, refused unless it declares this profile and has one Period."""
    if PROFILE_STGS not in mpd.profiles:
        raise MPDError(f"not a StreamSTGS manifest: @profiles lacks {PROFILE_STGS} "
                       f"(it lists {', '.join(p for p in mpd.profiles if p) or 'nothing'})")
    if len(mpd.periods) != 1:
        raise MPDError(f"a StreamSTGS MPD has exactly one Period, this one has {len(mpd.periods)}")
    return mpd


class StillPresentation:
    """A still scene's MPD (manifests/PROFILE.md, "A still scene"): the static-layer AdaptationSet alone, no GOP and
    no clock; a player shows the static layer from whatever viewpoint."""

    def __init__(self, mpd: MPD, url: str):
        self.mpd = _checked_mpd(mpd)
        self.url = url
        self.base = urljoin(url, mpd.base_url) if mpd.base_url else url
        found = still_static_set(mpd)
        if found is None:
            raise MPDError("a still scene's Period holds the static-layer AdaptationSet and no keyframe set")
        self.static: StaticLayerInfo = _static_layer(found)

    def static_url(self) -> str:
        """URL of the static-layer segment."""
        return urljoin(self.base, expand_template(self.static.media, self.static.rep_id, 0))

    def max_static_bytes(self) -> int:
        """The static segment's size cap: what its @bandwidth delivers over the Period, with slack."""
        return segment_cap(self.static.bandwidth, self.mpd.duration)

    def sibling_url(self, name: str) -> str:
        """URL of a document beside the MPD (stats.json, cameras.json)."""
        return urljoin(self.url, name)


def open_presentation(data: bytes, url: str, codec: str = "auto") -> Presentation | StillPresentation:
    """The MPD at `url` (its bytes `data`) as a still scene (no keyframe set) or a Presentation of GOPs."""
    mpd = _checked_mpd(parse_mpd(data))
    if still_static_set(mpd) is not None:
        return StillPresentation(mpd, url)
    return Presentation(mpd, url, codec)


def segment_cap(bandwidth: int, seconds: float) -> int:
    """A segment's size cap: what its @bandwidth delivers over its duration, with slack."""
    return min(MAX_SEGMENT_BYTES, math.ceil(bandwidth * seconds / 8 * SEGMENT_SLACK) + 4096)


class Presentation:
    """A parsed, checked StreamSTGS MPD with URL construction for every segment."""

    def __init__(self, mpd: MPD, url: str, codec: str = "auto"):
        """codec: which feature set to play where the tree offers two (FEATURE_CODEC_CHOICES)."""
        self.mpd = _checked_mpd(mpd)
        self.url = url
        self.base = urljoin(url, mpd.base_url) if mpd.base_url else url
        self.keyframes: AdaptationSet = mpd.adaptation_set(KEYFRAME_SCHEME)
        self.features: AdaptationSet
        self.feature_codec: FeatureCodec
        self.features, name = choose_feature_set(mpd, codec)
        self.feature_codec = CODECS[name]
        if not self.keyframes.representations:
            raise MPDError("the keyframe AdaptationSet has no Representation")
        self.keyframe_reps: dict[str, Representation] = {r.id: r for r in self.keyframes.representations}
        self.keyframe_quants = {r.id: keyframe_quant(r) for r in self.keyframes.representations}
        """Each keyframe Representation's quantisation (LOSSLESS for the top one)."""
        if not self.features.representations:
            raise MPDError("the feature AdaptationSet has no Representation")
        if self.features.segment_template.initialization is None:
            raise MPDError("the feature SegmentTemplate has no initialization")
        descriptor = KeyframeDescriptor.parse(self.keyframes)
        self.shape = GOPShape(descriptor.capacity, descriptor.gop_size, descriptor.window, descriptor.pe_freqs)
        self.fps = descriptor.fps
        self.segment_seconds = self.keyframes.segment_template.seconds
        if not 0 < self.segment_seconds <= 3600 or self.features.segment_template.seconds != self.segment_seconds:
            raise MPDError("keyframe and feature segments must have one positive duration")
        self.num_gops = gop_count(mpd.duration, self.segment_seconds)
        if self.num_gops > MAX_GOPS:
            raise MPDError(f"{self.num_gops} GOPs is over the client limit of {MAX_GOPS}")
        rungs = []
        for r in self.features.representations:
            kf = paired_keyframe(r, self.keyframe_reps)
            rungs.append(Rung(r.id, r.bandwidth, qp_of(r.id), QualityDescriptor.parse(r), kf.id, kf.bandwidth))
        self.ladder = sorted(rungs, key=lambda r: (r.total_bandwidth, r.rep_id))
        """Feature Representations, each with its keyframe Representation, by rising total bandwidth."""
        found = mpd.find_adaptation_set(STATIC_SCHEME)
        self.static: StaticLayerInfo | None = None if found is None else _static_layer(found)
        """The static layer of a format-2 presentation (fetched once, before the first GOP), or None."""

    @classmethod
    def parse(cls, data: bytes, url: str, codec: str = "auto") -> Presentation:
        return cls(parse_mpd(data), url, codec)

    @property
    def grid_side(self) -> int:
        return self.shape.grid_side

    @property
    def duration(self) -> float:
        return self.mpd.duration

    def gop_at(self, seconds: float) -> int:
        """The GOP that holds presentation time `seconds` (clamped to the last GOP)."""
        if not math.isfinite(seconds) or seconds < 0:
            raise MPDError(f"start time must be a non-negative number of seconds, got {seconds}")
        return min(self.num_gops - 1, int(seconds / self.segment_seconds + 1e-9))

    def span(self, start_s: float, duration_s: float | None, buffer_s: float | None) -> PlaybackSpan:
        """The GOPs and frames a playback from `start_s` (at its GOP's first frame) for `duration_s` (None: to
        the end) needs, and its buffer capacity (None: three GOPs)."""
        k0 = self.gop_at(start_s)
        g = self.shape.gop_size
        total = (self.num_gops - k0) * g
        frames = total if duration_s is None else max(1, min(total, round(duration_s * self.fps)))
        capacity = max(buffer_s if buffer_s is not None else 3 * self.segment_seconds, self.segment_seconds)
        return PlaybackSpan(k0, frames, list(range(k0, k0 + math.ceil(frames / g))), capacity)

    def _number(self, gop: int, template_start: int) -> int:
        if not 0 <= gop < self.num_gops:
            raise MPDError(f"GOP {gop} is outside 0..{self.num_gops - 1}")
        return template_start + gop

    def keyframe_url(self, gop: int, rep: str = KEYFRAME_REP) -> str:
        """URL of GOP `gop`'s segment of keyframe Representation `rep`."""
        t = self.keyframes.segment_template
        return urljoin(self.base, expand_template(t.media, self._keyframe_rep(rep).id,
                                                  self._number(gop, t.start_number)))

    def _keyframe_rep(self, rep: str) -> Representation:
        if rep not in self.keyframe_reps:
            raise MPDError(f"no keyframe Representation {rep!r}; the set has {', '.join(self.keyframe_reps)}")
        return self.keyframe_reps[rep]

    def abr_bandwidths(self) -> list[int]:
        """Per rung, the bit/s an ABR rule weighs: its features plus what its keyframes cost over the cheapest
        keyframes of the ladder (whose bits the rules budget apart, as AbrState.keyframe_bits)."""
        base = min(r.keyframe_bandwidth for r in self.ladder)
        return [r.bandwidth + r.keyframe_bandwidth - base for r in self.ladder]

    def static_url(self) -> str:
        """URL of the static-layer segment (format 2 only)."""
        if self.static is None:
            raise MPDError("this presentation has no static layer")
        return urljoin(self.base, expand_template(self.static.media, self.static.rep_id, 0))

    def max_static_bytes(self) -> int:
        """The static segment's size cap: what its @bandwidth delivers over the Period, with slack."""
        if self.static is None:
            raise MPDError("this presentation has no static layer")
        return segment_cap(self.static.bandwidth, self.duration)

    def init_url(self, rep_id: str) -> str:
        template = self.features.segment_template.initialization
        assert template is not None  # checked when the Presentation was built
        return urljoin(self.base, expand_template(template, rep_id))

    def media_url(self, rep_id: str, gop: int) -> str:
        t = self.features.segment_template
        return urljoin(self.base, expand_template(t.media, rep_id, self._number(gop, t.start_number)))

    def sibling_url(self, name: str) -> str:
        """URL of a document beside the MPD (stats.json, cameras.json)."""
        return urljoin(self.url, name)

    def check_feature_segment(self, init: bytes, media: bytes, gop: int) -> None:
        """Raise MP4Error unless the feature media segment sits at GOP `gop`'s place in the timeline: its tfdt,
        in the init segment's timescale, is gop x segment duration (manifests/PROFILE.md; a cache or server
        that answers with another GOP's segment would otherwise play the wrong motion silently)."""
        _, decode_time = media_timeline(media)
        seconds = decode_time / track_timescale(init)
        expected = gop * self.segment_seconds
        if abs(seconds - expected) >= self.segment_seconds / 2:
            raise MP4Error(f"the feature segment fetched for GOP {gop} starts at {seconds:.3f} s, expected "
                           f"{expected:.3f} s (GOP {round(seconds / self.segment_seconds)}'s place)")

    def decoded_gop_bytes(self, ring_frames: int) -> int:
        """Memory one decoded GOP holds at its peak: its canonical attributes twice (keyframe and model), a ring
        of `ring_frames` N x 16 float32 feature frames, and the video decoder's pictures (at most 16 of 4S x 4S
        16-bit: HEVC's largest picture buffer; AV1's 8 reference frames of 4:2:0 pictures take less)."""
        side = self.grid_side
        n = side * side
        return 2 * n * 14 * 4 + ring_frames * n * 16 * 4 + 16 * (4 * side) ** 2 * 2

    def static_layer_bytes(self) -> int:
        """Memory the decoded static layer holds for the whole playback (its attributes, its per-view copy for
        the renderer and the layered merge of one frame); 0 in format 1."""
        if self.static is None:
            return 0
        return 3 * self.static.capacity * (14 + 9 * self.static.sh_degree) * 4

    def max_keyframe_bytes(self, rep: str = KEYFRAME_REP) -> int:
        return segment_cap(self._keyframe_rep(rep).bandwidth, self.segment_seconds)

    def max_media_bytes(self, rep_id: str) -> int:
        return segment_cap(self.rung(rep_id).bandwidth, self.segment_seconds)


    def rung(self, rep_id: str) -> Rung:
        for r in self.ladder:
            if r.rep_id == rep_id:
                return r
        raise MPDError(f"no feature Representation {rep_id!r}; the ladder has "
                       f"{', '.join(r.rep_id for r in self.ladder)}")
