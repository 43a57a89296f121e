"""The playback log: one record per GOP and the document `stgs play` and `stgs sim` both write (docs/CLIENT.md)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from stgs.client.clock import PlaybackClock
from stgs.tree import KEYFRAME_REP

LOG_FORMAT = "streamstgs-playback"


@dataclass
class GOPRecord:
    """What happened to one GOP (one row of the playback log)."""

    index: int
    rep: str = ""
    qp: int | None = None
    rule: str = ""
    """Rule that chose the Representation (dynamic: which of its two)."""
    decisions: list[dict] = field(default_factory=list)
    """Every decision about this GOP's rung (the ABR choice, abandonment, fallbacks): rule, index, reason."""
    requests: list[dict] = field(default_factory=list)
    """Every request made for this GOP, in order: kind, rep and outcome."""
    buffer_s: float = 0.0
    """Buffer level when the choice was made."""
    estimate_kbps: float | None = None
    """Throughput estimate when the choice was made."""
    keyframe_bytes: int = 0
    keyframe_rep: str = KEYFRAME_REP
    """The keyframe Representation played (manifests/PROFILE.md, "Keyframe rungs")."""
    feature_bytes: int = 0
    init_bytes: int = 0
    static_bytes: int = 0
    """A layered scene's static-layer segment, counted in the first GOP of the playback (fetched once)."""
    static_decode_s: float = 0.0
    """Its decode (first GOP only)."""
    download_s: float = 0.0
    ttfb_s: float = 0.0
    """Time to first byte of the feature segment."""
    keyframe_decode_s: float = 0.0
    feature_decode_s: float = 0.0
    """HEVC decode of the GOP's feature frames (the sum of decode_ms where the player streams them)."""
    dequantise_s: float = 0.0
    decode_ms: list[float] = field(default_factory=list)
    """Per feature frame, in decode order: its HEVC decode (the decoder thread, beside the renderer)."""
    dequantise_ms: list[float] = field(default_factory=list)
    """Per feature frame: its untiling and dequantisation (0 for a frame released before it was decoded)."""
    decode_at_s: list[float] = field(default_factory=list)
    """Per feature frame: when its decode began (seconds since playback began)."""
    wait_ms: list[float] = field(default_factory=list)
    """Per rendered frame: how long the renderer waited for the frame's features."""
    render_at_s: list[float] = field(default_factory=list)
    """Per rendered frame: when its render began, waiting for features included (seconds since playback began)."""
    ring_peak: int = 0
    """Most feature frames the GOP's ring held at once."""
    boundary_wait_s: float = 0.0
    """Time the player waited at this GOP's start for it to be decoded (startup for the first)."""
    stall_s: float = 0.0
    render_ms: list[float] = field(default_factory=list)
    deform_ms: list[float] = field(default_factory=list)
    splat_ms: list[float] = field(default_factory=list)
    dropped: int = 0
    presented: int = 0
    """Frames whose time slot passed (rendered, dropped, or not decoded at all)."""
    fetch_start_s: float = 0.0
    """When the GOP's first request started (seconds since playback began)."""
    fetch_end_s: float | None = None
    """None until the GOP is downloaded."""
    play_start_s: float | None = None
    """When its first frame was due after any stall (seconds since playback began)."""
    latency_ms: list[float] = field(default_factory=list)
    """Round trips the network model applied to this GOP's requests (harness simulator only)."""
    abandoned_bytes: int = 0
    """Bytes of a feature download the ABR abandoned."""
    events: list[str] = field(default_factory=list)
    """Retries, fallbacks and abandonments, in words."""

    @property
    def decode_s(self) -> float:
        return self.keyframe_decode_s + self.feature_decode_s + self.dequantise_s


def gop_row(r: GOPRecord) -> dict:
    def mean(xs: list[float]) -> float | None:
        return sum(xs) / len(xs) if xs else None

    return {"index": r.index, "rep": r.rep, "qp": r.qp, "rule": r.rule, "buffer_s": r.buffer_s,
            "estimate_kbps": r.estimate_kbps, "keyframe_bytes": r.keyframe_bytes, "keyframe_rep": r.keyframe_rep,
            "feature_bytes": r.feature_bytes,
            "init_bytes": r.init_bytes, "static_bytes": r.static_bytes, "static_decode_s": r.static_decode_s,
            "download_s": r.download_s, "ttfb_s": r.ttfb_s,
            "keyframe_decode_s": r.keyframe_decode_s, "feature_decode_s": r.feature_decode_s,
            "dequantise_s": r.dequantise_s, "decode_s": r.decode_s, "decode_ms": r.decode_ms,
            "dequantise_ms": r.dequantise_ms, "decode_at_s": r.decode_at_s, "wait_ms": r.wait_ms,
            "render_at_s": r.render_at_s, "deform_ms": r.deform_ms,
            "splat_ms": r.splat_ms, "ring_peak": r.ring_peak, "boundary_wait_s": r.boundary_wait_s,
            "stall_s": r.stall_s, "fetch_start_s": r.fetch_start_s, "fetch_end_s": r.fetch_end_s,
            "play_start_s": r.play_start_s, "presented": r.presented, "render_ms": r.render_ms,
            "deform_ms_mean": mean(r.deform_ms), "splat_ms_mean": mean(r.splat_ms), "dropped": r.dropped,
            "latency_ms": r.latency_ms, "abandoned_bytes": r.abandoned_bytes, "events": r.events,
            "decisions": r.decisions, "requests": r.requests}


def playback_log(records: list[GOPRecord], clock: PlaybackClock, *, url: str, abr: str, wasted_bytes: int,
                 retries: int, error: BaseException | str | None, gops_planned: int, extra: dict | None = None) -> dict:
    """The log document of one playback (records of every planned GOP, in order)."""
    recs = [r for r in records if r.rep]
    played = [r for r in recs if r.presented]
    render = sorted(ms for r in played for ms in r.render_ms)
    reps = [r.rep for r in played]
    frames = sum(r.presented for r in played)
    total_bytes = sum(r.keyframe_bytes + r.feature_bytes + r.init_bytes + r.static_bytes for r in played)
    return {
        "format": LOG_FORMAT, "version": 1, "url": url, "abr": abr, **(extra or {}),
        "segment_s": clock.segment_s, "buffer_capacity_s": clock.capacity_s, "start_gop": clock.first_gop,
        "gops_planned": gops_planned, "gops_played": len(played),
        "startup_delay_s": records[0].boundary_wait_s if clock.t0 is not None else None,
        "stalls": {"count": sum(1 for r in played if r.stall_s > 0), "total_s": clock.stall_total},
        "switches": sum(1 for a, b in itertools.pairwise(reps) if a != b),
        "frames": frames, "rendered_frames": len(render), "dropped_frames": sum(r.dropped for r in played),
        "render_ms_median": render[len(render) // 2] if render else None,
        "render_fps": 1e3 / render[len(render) // 2] if render else None,
        "static_bytes": sum(r.static_bytes for r in recs),
        "bytes": total_bytes, "kb_per_frame": total_bytes / 1e3 / frames if frames else None,
        "wasted_bytes": wasted_bytes, "retries": retries,
        "error": None if error is None else str(error) or type(error).__name__,
        "gops": [gop_row(r) for r in recs],
    }
