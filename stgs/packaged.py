"""A packaged tree read back from disk as a player decodes it: per feature Representation its GOP models (keyframe of
the paired keyframe Representation, features decoded from the video), and its static layer. For `stgs eval --dash`,
`stgs export` from a tree and the tests that hold a player's frames to the packager's."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from stgs.codec.features import features_from_frames
from stgs.codec.keyframe import decode_keyframe
from stgs.codec.static import decode_static
from stgs.codec.video import CODECS, FeatureCodec, decode_segment
from stgs.errors import MPDError, StgsError
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.static import StaticLayer
from stgs.mpd.model import AdaptationSet, Representation, read_mpd
from stgs.mpd.profile import (
    FEATURE_SCHEME,
    KEYFRAME_SCHEME,
    STATIC_SCHEME,
    KeyframeDescriptor,
    StaticLayerDescriptor,
    feature_set_codec,
    keyframe_quant,
    paired_keyframe,
)
from stgs.tree import MANIFEST, expand_template


def packaged_static(dash: Path) -> StaticLayer | None:
    """A local format-2 tree's static layer as a player decodes it (None for a format-1 tree)."""
    try:
        found = read_mpd(dash / MANIFEST).find_adaptation_set(STATIC_SCHEME)
        if found is None:
            return None
        descriptor = StaticLayerDescriptor.parse(found)
        data = (dash / expand_template(found.segment_template.media, found.representations[0].id, 0)).read_bytes()
        return decode_static(data, descriptor.capacity, descriptor.sh_degree, len(data))
    except (OSError, MPDError, IndexError, ValueError) as exc:
        raise StgsError(f"{dash}: static layer unreadable ({exc})") from None


def packaged_gops(dash: Path) -> dict[str, Callable[[int], GOPModel]]:
    """Representation id -> (GOP index -> the GOP as a player decodes it) for a local DASH tree, over every feature
    set (HEVC and AV1)."""
    try:
        mpd = read_mpd(dash / MANIFEST)
        kf_set = mpd.adaptation_set(KEYFRAME_SCHEME)
        videos = [(a, CODECS[feature_set_codec(a)]) for a in mpd.adaptation_sets(FEATURE_SCHEME)]
    except (OSError, MPDError) as exc:
        raise StgsError(f"{dash}: not a packaged scene ({exc})") from None
    try:
        d = KeyframeDescriptor.parse(kf_set)
    except MPDError as exc:
        raise StgsError(f"{dash}: {exc}") from None
    shape = GOPShape(d.capacity, d.gop_size, d.window, d.pe_freqs)
    side = shape.grid_side

    keyframe_reps = {r.id: r for r in kf_set.representations}

    def loader(video: AdaptationSet, codec: FeatureCodec, rep: Representation) -> Callable[[int], GOPModel]:
        template = video.segment_template.initialization
        if template is None:
            raise StgsError(f"{dash}: the feature SegmentTemplate has no initialization")
        init = (dash / expand_template(template, rep.id)).read_bytes()
        try:
            paired = paired_keyframe(rep, keyframe_reps)
            quant = keyframe_quant(paired)
        except MPDError as exc:
            raise StgsError(f"{dash}: {exc}") from None

        def load(k: int) -> GOPModel:
            n = kf_set.segment_template.start_number + k
            data = (dash / expand_template(kf_set.segment_template.media, paired.id, n)).read_bytes()
            kf = decode_keyframe(data, shape, k, len(data), quant)
            media = (dash / expand_template(video.segment_template.media, rep.id, n)).read_bytes()
            frames = decode_segment(init, media, shape.num_features, 4 * side, 4 * side, codec=codec)
            return kf.to_model(features_from_frames(frames, side, kf.feature_ranges, codec.bits))

        return load

    return {r.id: loader(video, codec, r) for video, codec in videos for r in video.representations}
