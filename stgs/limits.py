"""Every size cap of the system, in one place (docs/ARCHITECTURE.md, "Security": sizes are checked before allocation).

A model dir, a manifest and a keyframe segment are all checked against these
same numbers, so whatever `stgs train`/`stgs synth` may write, `stgs pack`
accepts and `stgs play` decodes.
"""

# --- scene shape (model.json, the keyframe descriptor of an MPD) ---
MAX_CAPACITY = 1 << 22
"""Most Gaussians per GOP (4 M slots: about 1 GiB of float32 features per GOP at G = 60)."""
MAX_GOP_SIZE = 1024
"""Most frames per GOP."""
MAX_WINDOW = 16
"""Longest sliding window W of temporal features per frame (the native fp32 kernel takes all of them)."""
MAX_BF16_WINDOW = 8
"""Longest window the bf16 deformation kernel takes (its D_t input is padded to 128 = 8 x 16 lanes)."""
MAX_PE_FREQS = 16
"""Most positional-encoding frequencies of t."""
MIN_FPS = 1.0
"""Slowest frame rate a scene may have (the video timing needs a positive rate at 1/1001 precision)."""
MAX_FPS = 1000.0
"""Fastest frame rate a scene may have."""
MAX_GOPS = 100_000
"""Most GOPs per scene (55 hours at 2-second GOPs)."""

# --- images ---
MAX_IMAGE_SIDE = 16_384
"""Largest width or height the splatter renders, and a camera may ask for."""
MAX_PATH_CAMERAS = 100_000
"""Most cameras in a camera path or a scene's cameras.json."""

# --- documents and segments fetched over the network ---
MAX_MPD_BYTES = 1 << 20
"""Largest manifest accepted."""
MAX_DOC_BYTES = 16 << 20
"""Largest stats.json, cameras.json or scene.json accepted."""
MAX_TITLE_CHARS = 200
"""Longest scene title (stgs pack --title)."""
MAX_DESCRIPTION_CHARS = 4000
"""Longest scene description (stgs pack --description)."""
MAX_POSTER_BYTES = 4 << 20
"""Largest poster image a player fetches."""
MAX_KEYFRAME_HEADER_BYTES = 1 << 20
"""Largest safetensors header of a keyframe segment."""
MAX_SEGMENT_BYTES = 1 << 30
"""Fixed cap on any segment, whatever the manifest says."""
MAX_INIT_BYTES = 1 << 20
"""Largest init segment of a feature Representation."""
SEGMENT_SLACK = 1.25
"""A segment may exceed @bandwidth x duration by this factor (the packager's @bandwidth covers the largest)."""
MAX_DURATION_S = 10 * 366 * 86400.0
"""Longest duration an MPD may state (ten years: any real presentation, and finite arithmetic after it)."""
MAX_TEMPLATE_NUMBER_WIDTH = 32
"""Widest `$Number%0Nd$` a segment template may ask for (DASH's widths are a handful of digits)."""

# --- harness inputs ---
MAX_TRACE_POINTS = 1_000_000
"""Most points of one bandwidth trace."""
MAX_TRACE_FILES = 10_000
"""Most trace files in one recorded trace set (a folder)."""
