"""The StreamSTGS profile's descriptors in an MPD (manifests/PROFILE.md): the schemes that mark its
AdaptationSets and the keyframe and static-layer SupplementalProperty values, written and checked in one place."""

from __future__ import annotations

import math
from dataclasses import dataclass

from stgs.limits import MAX_CAPACITY, MAX_FPS, MAX_GOP_SIZE, MAX_PE_FREQS, MAX_WINDOW, MIN_FPS
from stgs.mpd import AdaptationSet
from stgs.mpd_values import MPDError

KEYFRAME_SCHEME = "urn:streamstgs:keyframe:2026"
"""SupplementalProperty scheme marking the keyframe AdaptationSet."""
FEATURE_SCHEME = "urn:streamstgs:features:2026"
"""SupplementalProperty scheme marking the feature-video AdaptationSet."""
STATIC_SCHEME = "urn:streamstgs:static:2026"
"""SupplementalProperty scheme marking the static-layer AdaptationSet (format-2 trees only)."""


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
