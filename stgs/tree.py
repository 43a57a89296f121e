"""File names of a packaged scene (manifests/PROFILE.md): what `stgs pack` writes and `stgs play` reads."""

MANIFEST = "manifest.mpd"
"""The MPD, written last."""
STATS = "stats.json"
"""Per-GOP, per-Representation sizes and quality (stgs pack)."""
CAMERAS = "cameras.json"
"""The scene's cameras, when the model dir has them: {"format", "version", "cameras": [Camera.to_json()]}."""
CAMERAS_FORMAT = "streamstgs-cameras"
