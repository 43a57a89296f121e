"""Compression of GOP models for streaming: PLAS grids, attribute images (lossless JPEG XL),
feature tiling and video (HEVC in-process via PyAV), the keyframe container and MP4 segment handling.

The packager writes with these modules and the client reads with them: they are
the one place each on-the-wire format is defined (docs in manifests/PROFILE.md).
"""
