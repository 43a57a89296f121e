"""stgs.packager: model dir -> MPEG-DASH tree (`stgs pack`); the profile is in manifests/PROFILE.md."""

from stgs.codec.video import DEFAULT_QPS
from stgs.packager.packer import MANIFEST, STATS, PackConfig, pack

__all__ = ["DEFAULT_QPS", "MANIFEST", "STATS", "PackConfig", "pack"]
