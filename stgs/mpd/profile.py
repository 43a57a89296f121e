"""The StreamSTGS profile's descriptors in an MPD (manifests/PROFILE.md): the schemes that mark its
AdaptationSets and the keyframe and static-layer SupplementalProperty values, written and checked in one place."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from stgs.codec import FEATURE_CODECS
from stgs.codec.quant import LOSSLESS, KeyframeQuant
from stgs.errors import FieldError, MPDError
from stgs.limits import MAX_CAPACITY, MAX_FPS, MAX_GOP_SIZE, MAX_PE_FREQS, MAX_WINDOW, MIN_FPS
from stgs.mpd.model import MPD, AdaptationSet, Representation

KEYFRAME_SCHEME = "urn:streamstgs:keyframe:2026"
"""SupplementalProperty scheme marking the keyframe AdaptationSet."""
FEATURE_SCHEME = "urn:streamstgs:features:2026"
"""SupplementalProperty scheme marking the feature-video AdaptationSet."""
STATIC_SCHEME = "urn:streamstgs:static:2026"
"""SupplementalProperty scheme marking the static-layer AdaptationSet (format-2 trees only)."""
QUALITY_SCHEME = "urn:streamstgs:quality:2026"
"""SupplementalProperty scheme of a feature Representation's measured quality."""
KEYFRAME_QUANT_SCHEME = "urn:streamstgs:keyframe-quant:2026"
"""SupplementalProperty scheme of a lossy keyframe Representation: the bits of each image
(stgs.codec.quant.KeyframeQuant.value). The lossless Representation has none."""
FEATURE_CODEC_CHOICES = ("auto", *FEATURE_CODECS)
"""What a player may ask for: a codec's feature set, or auto (HEVC where the tree has it, else AV1)."""


@dataclass(frozen=True)
class KeyframeDescriptor:
    """The keyframe AdaptationSet's SupplementalProperty (manifests/PROFILE.md): the sizes of every GOP of the
    scene, which a player checks before it downloads anything. `value` writes it, `parse` reads and checks it."""

    capacity: int
    """N = S² Gaussians per GOP (the dynamic layer's, in a format-2 tree)."""
    gop_size: int
    """Frames per GOP."""
    window: int
    """Temporal window of the deformation field."""
    pe_freqs: int
    """Positional-encoding frequencies of the deformation field."""
    fps: float
    """Frames per second."""

    @property
    def grid_side(self) -> int:
        return math.isqrt(self.capacity)

    @property
    def value(self) -> str:
        return (f"version=1;capacity={self.capacity};grid_side={self.grid_side};gop_size={self.gop_size};"
                f"window={self.window};pe_freqs={self.pe_freqs};fps={self.fps:g}")

    @classmethod
    def parse(cls, adaptation_set: AdaptationSet) -> KeyframeDescriptor:
        """The descriptor of the keyframe AdaptationSet, refused (MPDError) unless it is version 1 with a square
        capacity and every size within the client's limits (stgs.limits)."""
        what = "keyframe"
        fields, capacity = _grid_fields(adaptation_set, KEYFRAME_SCHEME, what)
        try:
            fps = float(fields["fps"])
        except (KeyError, ValueError):
            raise MPDError("keyframe descriptor lacks fps") from None
        if not MIN_FPS <= fps <= MAX_FPS:  # also refuses nan
            raise MPDError(f"keyframe descriptor fps={fps} is outside {MIN_FPS:g}..{MAX_FPS:g}")
        return cls(capacity, bounded_field(fields, "gop_size", 2, MAX_GOP_SIZE, what),
                   bounded_field(fields, "window", 1, MAX_WINDOW, what),
                   bounded_field(fields, "pe_freqs", 0, MAX_PE_FREQS, what), fps)


@dataclass(frozen=True)
class StaticLayerDescriptor:
    """The static-layer AdaptationSet's SupplementalProperty (manifests/PROFILE.md): what a player must know
    before it fetches the layer. `value` writes it, `parse` reads and checks it (the one place for both)."""

    capacity: int
    """N_s = S_s² Gaussians."""
    sh_degree: int
    """0, or 1 with degree-1 view-dependent colour."""

    @property
    def grid_side(self) -> int:
        return math.isqrt(self.capacity)

    @property
    def value(self) -> str:
        return f"version=1;capacity={self.capacity};grid_side={self.grid_side};sh_degree={self.sh_degree}"

    @classmethod
    def parse(cls, adaptation_set: AdaptationSet) -> StaticLayerDescriptor:
        """The descriptor of a static-layer AdaptationSet, refused (MPDError) unless it is version 1 with a square
        capacity within MAX_CAPACITY and a known colour degree."""
        what = "static-layer"
        fields, capacity = _grid_fields(adaptation_set, STATIC_SCHEME, what)
        return cls(capacity, bounded_field(fields, "sh_degree", 0, 1, what))


@dataclass(frozen=True)
class FeatureDescriptor:
    """A feature-video AdaptationSet's SupplementalProperty (manifests/PROFILE.md): the tiling and the code depth
    of its frames (12 for the HEVC set, 10 for the AV1 set). `value` writes it, `parse` reads and checks it."""

    bits: int
    """Code depth of the feature frames."""

    @property
    def value(self) -> str:
        return f"tiles=4x4;channels=16;bits={self.bits}"

    @classmethod
    def parse(cls, adaptation_set: AdaptationSet) -> FeatureDescriptor:
        """The descriptor of a feature-video AdaptationSet, refused (MPDError) unless it is the 4x4 tiling of 16
        channels at a code depth this client dequantises."""
        fields = adaptation_set.descriptor(FEATURE_SCHEME).fields()
        if fields.get("tiles") != "4x4" or fields.get("channels") != "16":
            raise MPDError(f"feature descriptor of AdaptationSet {adaptation_set.id}: tiles={fields.get('tiles')!r} "
                           f"channels={fields.get('channels')!r} is not the 4x4 tiling of 16 channels")
        bits = bounded_field(fields, "bits", 1, 16, "feature") if "bits" in fields else 12
        if bits not in {b for _, b in FEATURE_CODECS.values()}:
            raise MPDError(f"feature descriptor bits={bits}: this client dequantises "
                           f"{' or '.join(str(b) for _, b in FEATURE_CODECS.values())}-bit codes")
        return cls(bits)



@dataclass(frozen=True)
class QualityDescriptor:
    """A feature Representation's SupplementalProperty (manifests/PROFILE.md): the mean PSNR of views rendered from
    the decoded stream against the uncompressed model at the scene's cameras and, where the packager knew the
    model's own error, the PSNR a viewer gets against the capture (stats.json has both per GOP). `value` writes
    it, `parse` reads and checks it."""

    render_psnr: float
    """dB against the uncompressed model."""
    truth_psnr: float | None = None
    """dB against the capture (estimated), or None."""

    @property
    def value(self) -> str:
        truth = "" if self.truth_psnr is None else f";truth_psnr={self.truth_psnr:.2f}"
        return f"render_psnr={self.render_psnr:.2f}{truth}"

    @classmethod
    def parse(cls, representation: Representation) -> QualityDescriptor | None:
        """The Representation's quality descriptor (None where it has none, as in older trees), refused
        (MPDError) unless each PSNR it gives is a number in 0..99 dB (render_psnr always)."""
        found = representation.find_descriptor(QUALITY_SCHEME)
        if found is None:
            return None
        fields = found.fields()

        def psnr(key: str, optional: bool) -> float | None:
            raw = fields.get(key)
            if raw is None and optional:
                return None
            if raw is None or not re.fullmatch(r"\d{1,2}(\.\d{1,6})?", raw):
                raise MPDError(f"quality descriptor of Representation {representation.id}: {key}={raw!r:.40} is "
                               "not a number in 0..99 dB")
            return float(raw)

        render = psnr("render_psnr", optional=False)
        assert render is not None  # psnr() refuses a missing one
        return cls(render, psnr("truth_psnr", optional=True))

    @property
    def quality(self) -> float:
        """The figure a viewer's choice rests on: against the capture where known, else against the model."""
        return self.render_psnr if self.truth_psnr is None else self.truth_psnr


def keyframe_quant(representation: Representation) -> KeyframeQuant:
    """A keyframe Representation's quantisation: its KEYFRAME_QUANT_SCHEME descriptor's, LOSSLESS without one
    (MPDError for a bad value)."""
    found = representation.find_descriptor(KEYFRAME_QUANT_SCHEME)
    if found is None:
        return LOSSLESS
    try:
        return KeyframeQuant.parse(found.value or "")
    except FieldError as exc:
        raise MPDError(f"keyframe Representation {representation.id}: {exc}") from None


def paired_keyframe(representation: Representation, keyframes: dict[str, Representation]) -> Representation:
    """The keyframe Representation (of `keyframes`, by id) a feature Representation plays with: the one its
    @associationId names, exactly one (MPDError otherwise)."""
    named = [a for a in representation.association_id if a in keyframes]
    if len(named) != 1:
        raise MPDError(f"feature Representation {representation.id} must name one keyframe Representation in "
                       f"@associationId (of {', '.join(keyframes)}), it names "
                       f"{' '.join(representation.association_id) or 'none'}")
    return keyframes[named[0]]


DURATION_PRECISION_S = 1e-3
"""@mediaPresentationDuration is written to the millisecond: a GOP that starts within this of its end is rounding."""


def gop_count(duration_s: float, segment_seconds: float) -> int:
    """GOPs of a presentation of `duration_s` cut into segments of `segment_seconds` (at least one)."""
    return max(1, math.ceil((duration_s - DURATION_PRECISION_S) / segment_seconds))


def feature_set_codec(a: AdaptationSet) -> str:
    """The codec (a FEATURE_CODECS name) of a feature AdaptationSet, from its Representations' @codecs (one
    codec per set), checked against the code depth its descriptor announces (MPDError otherwise)."""
    names = set()
    for r in a.representations:
        entry = (r.codecs or a.codecs or "").split(".")[0]
        names.add(next((n for n, (entries, _) in FEATURE_CODECS.items() if entry in entries), None))
    if len(names) != 1 or None in names:
        listed = sorted({r.codecs or a.codecs or "none" for r in a.representations})
        raise MPDError(f"feature AdaptationSet {a.id}: @codecs {', '.join(listed)} is not one codec this client "
                       "plays (hvc1/hev1: HEVC, av01: AV1)")
    name = names.pop()
    assert name is not None  # refused above
    bits = FeatureDescriptor.parse(a).bits
    if bits != FEATURE_CODECS[name][1]:
        raise MPDError(f"feature AdaptationSet {a.id}: {name} carries {FEATURE_CODECS[name][1]}-bit codes, its "
                       f"descriptor says bits={bits}")
    return name


def choose_feature_set(mpd: MPD, codec: str = "auto") -> tuple[AdaptationSet, str]:
    """The feature AdaptationSet a player of `codec` (FEATURE_CODEC_CHOICES) plays, and its codec's name."""
    if codec not in FEATURE_CODEC_CHOICES:
        raise MPDError(f"codec must be one of {', '.join(FEATURE_CODEC_CHOICES)}, got {codec!r}")
    sets = mpd.adaptation_sets(FEATURE_SCHEME)
    if not sets:
        raise MPDError(f"no AdaptationSet with SupplementalProperty {FEATURE_SCHEME}")
    found: dict[str, AdaptationSet] = {}
    for a in sets:
        name = feature_set_codec(a)
        if name in found:
            raise MPDError(f"two feature AdaptationSets ({found[name].id}, {a.id}) of one codec, {name}")
        found[name] = a
    want = next(n for n in FEATURE_CODECS if n in found) if codec == "auto" else codec
    if want not in found:
        raise MPDError(f"the manifest has no {want} feature set (it offers {', '.join(found)})")
    return found[want], want


def still_static_set(mpd: MPD) -> AdaptationSet | None:
    """A still scene's one static-layer AdaptationSet (manifests/PROFILE.md, "A still scene": the static set and no
    keyframe set), or None for a scene of GOPs. MPDError for a still with a feature set or two static sets."""
    if mpd.find_adaptation_set(KEYFRAME_SCHEME) is not None:
        return None
    statics = mpd.adaptation_sets(STATIC_SCHEME)
    if not statics:
        return None
    if mpd.find_adaptation_set(FEATURE_SCHEME) is not None:
        raise MPDError("a still scene (no keyframe AdaptationSet) has no feature set either")
    if len(statics) > 1:
        raise MPDError("the MPD has more than one static-layer AdaptationSet")
    return statics[0]


def _grid_fields(adaptation_set: AdaptationSet, scheme: str, what: str) -> tuple[dict[str, str], int]:
    """The `key=value` fields of a version-1 descriptor of a square grid of Gaussians, and its checked capacity."""
    fields = adaptation_set.descriptor(scheme).fields()
    if fields.get("version") != "1":
        raise MPDError(f"{what} descriptor version {fields.get('version')!r} is not supported (this client reads "
                       "version 1)")
    capacity = bounded_field(fields, "capacity", 1, MAX_CAPACITY, what)
    side = bounded_field(fields, "grid_side", 1, math.isqrt(MAX_CAPACITY), what)
    if side * side != capacity:
        raise MPDError(f"{what} descriptor: grid_side {side} does not match capacity {capacity}")
    return fields, capacity


def bounded_field(fields: dict[str, str], key: str, lo: int, hi: int, what: str) -> int:
    """Integer `key` of a descriptor's `key=value` fields within lo..hi (the client's caps); `what` names the
    descriptor in the error."""
    try:
        value = int(fields[key])
    except (KeyError, ValueError):
        raise MPDError(f"{what} descriptor lacks an integer {key}") from None
    if not lo <= value <= hi:
        raise MPDError(f"{what} descriptor {key}={value} is outside {lo}..{hi} (client limit)")
    return value
