"""Compression of GOP models for streaming: PLAS grids, attribute images (lossless JPEG XL),
feature tiling and video (HEVC in-process via PyAV), the keyframe container and MP4 segment handling.

The packager writes with these modules and the client reads with them: they are
the one place each on-the-wire format is defined (docs in manifests/PROFILE.md).
"""

FEATURE_CODECS = {"hevc": (("hvc1", "hev1"), 12), "av1": (("av01",), 10)}
"""The feature-video codecs a tree may carry, one AdaptationSet each, reference first: the @codecs sample entries
that name each and the code depth of its frames."""
