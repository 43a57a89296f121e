"""What one playback needs (one config object flows through a run) and the error that ends one."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from stgs.client.abr import RULES, AbrSettings
from stgs.client.clock import RENDER_AHEAD
from stgs.client.fetch.download import DownloadSettings
from stgs.client.urlpolicy import UrlPolicySettings
from stgs.errors import FieldError, NativeUnavailableError, StgsError
from stgs.limits import MAX_IMAGE_SIDE
from stgs.mpd.profile import FEATURE_CODEC_CHOICES


@dataclass
class ViewSpec:
    """The viewpoint options of `stgs play` (exactly one of camera / eye / path is used)."""

    camera: str | None = None
    """Name of a camera of the scene (cameras.json beside the MPD)."""
    eye: tuple[float, float, float] | None = None
    """Explicit camera position (with `target`)."""
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Point an explicit camera looks at."""
    path: str = "orbit"
    """'orbit' (a circle inside a surrounding capture rig, else framing the scene) or a JSON file: a list of
    cameras (Camera.to_json) played in turn."""
    orbit_seconds: float | None = None
    """Seconds per orbit turn (None: the whole playback)."""
    width: int | None = None
    """Image width (None: the scene camera's, else 640)."""
    height: int | None = None
    """Image height (None: the scene camera's, else 360)."""
    fov_deg: float = 60.0
    """Horizontal field of view of explicit and orbit cameras."""

    def size(self, default: tuple[int, int] = (640, 360)) -> tuple[int, int]:
        w, h = self.width or default[0], self.height or default[1]
        if not (1 <= w <= MAX_IMAGE_SIDE and 1 <= h <= MAX_IMAGE_SIDE):
            raise StgsError(f"image size {w}x{h} is outside 1..{MAX_IMAGE_SIDE}")
        return w, h


class PlaybackError(StgsError):
    """Playback could not go on (after the retries and fallbacks the log records)."""


@dataclass
class PlayConfig:
    """Everything one playback needs (one config object flows through a run)."""

    url: str
    """URL of the MPD."""
    abr: str = "mpc"
    """ABR rule: mpc, dynamic, throughput, bola or bola-e (stgs/client/abr/rules.py)."""
    qp: int | None = None
    """Pin the feature Representation of this ladder point (HEVC QP, AV1 QP; no adaptation)."""
    codec: str = "auto"
    """Feature set to play where the tree offers two: auto (HEVC where present, else AV1), hevc or av1."""
    buffer_s: float | None = None
    """Most media seconds downloaded ahead (None: three GOPs)."""
    start_s: float = 0.0
    """Start at the GOP holding this presentation time."""
    duration_s: float | None = None
    """Seconds to play (None: to the end)."""
    realtime: bool = False
    """Pace frames to the clock and drop the ones rendering cannot make; else render every frame at full speed."""
    view: ViewSpec = field(default_factory=ViewSpec)
    """Viewpoint."""
    out: Path | None = None
    """PNG folder or .mp4 file (None: frames are not written)."""
    log: Path | None = None
    """Where to write the JSON playback log."""
    native: bool | None = None
    """Native deform + splat (None: when built)."""
    precision: str = "fp32"
    """Arithmetic of the native deformation: fp32, bf16 (faster where the CPU has AVX512-BF16 or AMX) or int16
    (faster on AVX2 CPUs); the last two cost accuracy (stgs.model.precision.PRECISIONS)."""
    max_decoded: int = 2
    """Decoded GOP models held at once (the one playing + pre-decoded ones)."""
    ring_frames: int = 8
    """Feature frames decoded ahead of the renderer, per GOP (at least the model's window W)."""
    render_ahead: int = RENDER_AHEAD
    """Frame slots a frame may be rendered before its own (real time): a frame slower than a slot borrows the
    time the frames before it left, and the first GOP (or one after a stall) is shown that many slots after
    it is ready; the camera's motion is that many frames late on screen (0: each frame renders in its own
    slot)."""
    render_threads: int | None = None
    """Threads of the deform and splat kernels (None: every usable core; stgs.client.threads)."""
    decode_threads: int | None = None
    """libavcodec threads of the feature decoder (None: 1 below eight cores, else 2)."""
    decode: bool = True
    """Decode and render (False: network and buffer only, for emulation and load tests)."""
    speed: float = 1.0
    """Media seconds per wall second of the playback clock (> 1: scaled-time emulation; decode off only)."""
    abr_settings: AbrSettings = field(default_factory=AbrSettings)
    download: DownloadSettings = field(default_factory=DownloadSettings)
    urls: UrlPolicySettings = field(default_factory=UrlPolicySettings)
    """Which hosts and addresses the player may fetch from besides the manifest's (stgs.client.urlpolicy)."""

    def validate(self) -> None:
        if self.codec not in FEATURE_CODEC_CHOICES:
            raise FieldError("codec", f"must be one of {', '.join(FEATURE_CODEC_CHOICES)}, got {self.codec!r}")
        if self.abr not in RULES:
            raise FieldError("abr", f"must be one of {', '.join(RULES)}, got {self.abr!r}")
        if self.buffer_s is not None and not self.buffer_s > 0:
            raise FieldError("buffer_s", "must be a positive number of seconds")
        if not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise FieldError("start_s", "must be a non-negative number of seconds")
        if self.duration_s is not None and not self.duration_s > 0:
            raise FieldError("duration_s", "must be a positive number of seconds")
        if self.ring_frames < 1:
            raise FieldError("ring_frames", "must be >= 1 (and at least the model's window)")
        if self.render_ahead < 0:
            raise FieldError("render_ahead", "must be >= 0 frames")
        for name in ("render_threads", "decode_threads"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise FieldError(name, "must be >= 1")
        if self.max_decoded < 2:
            raise FieldError("max_decoded", "must be >= 2 (the GOP playing and the next)")
        if not (math.isfinite(self.speed) and self.speed > 0) or (self.speed != 1 and self.decode):
            raise FieldError("speed", "must be positive, and other than 1 only without decoding")
        if self.decode:
            from stgs.model.native_deform import check_precision  # torch: only where the playback will decode

            try:
                check_precision(self.precision)
            except (ValueError, NativeUnavailableError) as err:
                raise FieldError("precision", str(err)) from None
            if self.precision != "fp32" and self.native is False:
                raise FieldError("precision", "other than fp32 needs the native renderer")


