"""Settings of `stgs serve` and what follows from them: the served types, cache lifetimes, CORS, app keys."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from aiohttp import web

from stgs.errors import FieldError
from stgs.server.clients import Network, trusted_networks
from stgs.server.slots import TransferSlots, per_client_slots
from stgs.tree import KEYFRAME_EXTENSION, KEYFRAME_MIME_TYPE, STATIC_EXTENSION, STATIC_MIME_TYPE

if TYPE_CHECKING:
    from stgs.server.metrics import Metrics  # which imports this module

CONTENT_TYPES = {
    ".mpd": "application/dash+xml",
    ".mp4": "video/mp4",
    ".m4s": "video/iso.segment",
    KEYFRAME_EXTENSION: KEYFRAME_MIME_TYPE,
    STATIC_EXTENSION: STATIC_MIME_TYPE,
    ".json": "application/json",
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".wasm": "application/wasm",
    ".css": "text/css; charset=utf-8",
    ".webp": "image/webp",
}
"""The only files served, by extension."""


MUTABLE_SUFFIXES = (".mpd", ".json", ".html")
"""Mutable documents: short cache lifetime. Everything else is an immutable segment (or a content-hashed asset of
the web player, when a tree is served with the built player beside it)."""


CORS_HEADERS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Expose-Headers": "Content-Length, Content-Range, ETag, Last-Modified, Accept-Ranges",
}


ROOT_KEY = web.AppKey("root", Path)


METRICS_KEY: web.AppKey[Metrics] = web.AppKey("metrics")


SLOTS_KEY = web.AppKey("slots", TransferSlots)


HEADERS_KEY = web.AppKey("headers", dict[str, dict[str, str]])
"""Response headers by file suffix (response_headers)."""


@dataclass
class ServeConfig:
    """Settings of one server."""

    root: Path
    """Folder of packaged scenes (each a folder with manifest.mpd), or one packaged scene."""
    host: str = "127.0.0.1"
    """Listen address (loopback by default)."""
    port: int = 8080
    """Listen port (0: any free port)."""
    max_transfers: int = 512
    """File transfers sending at once, server-wide; further requests wait for a slot (stgs.server.slots)."""
    max_transfers_per_client: int | None = None
    """File transfers sending at once for one client address: at most a quarter of max_transfers (None: 32, or
    that quarter when it is smaller)."""
    max_waiting_transfers: int = 1024
    """Transfers parked on a socket that takes no bytes (they hold no slot); one more cuts the parked transfer
    with the least recent progress. Each holds 3 file descriptors: the process's limit is raised to fit."""
    trusted_proxies: tuple[str, ...] = ()
    """Address ranges (CIDR) of proxies whose X-Forwarded-For / Forwarded name the client; from anyone else
    those headers are ignored."""
    send_timeout: float = 30.0
    """Seconds a transfer may go without the client taking a byte before its connection is reset."""
    keepalive_timeout: float = 15.0
    """Seconds an idle keep-alive connection stays open."""
    max_header_bytes: int = 8190
    """Longest request line / header field accepted (longer: 400)."""
    max_headers: int = 64
    """Most header fields per request."""
    max_head_bytes: int = 32_768
    """Bytes the request line and all header fields of one request may take together (more: 431, closed)."""
    max_connections_per_client: int = 128
    """Open connections one client address may hold (more: 503, closed; 0: no limit)."""
    shutdown_timeout: float = 10.0
    """On SIGTERM, seconds in-flight transfers get to finish before they are cut."""
    manifest_max_age: int = 2
    """Cache-Control max-age of MPDs and stats (seconds)."""
    segment_max_age: int = 31_536_000
    """Cache-Control max-age of segments (they never change under one URL)."""
    access_log: bool = True
    """Write one JSON line per request to stderr."""
    workers: int = 1
    """Server processes sharing the port (SO_REUSEPORT: the kernel spreads connections); /metrics sums them all."""
    player_dir: Path | None = None
    """The built web player served at /player/ (None: web/dist of this checkout)."""
    io_threads: int | None = 0
    """Threads for each file's stat/open/close: 0 does them on the event loop (microseconds on a local disk,
    far less than a hop to a thread), N uses N threads (slow network storage), None leaves the loop's
    default executor alone (a server sharing its loop with other code, like the demo's player)."""
    trusted: tuple[Network, ...] = field(init=False, repr=False)
    """trusted_proxies, parsed."""

    def __post_init__(self) -> None:
        for name in ("max_transfers", "max_waiting_transfers"):
            if getattr(self, name) < 1:
                raise FieldError(name, f"must be at least 1, got {getattr(self, name)}")
        self.max_transfers_per_client = per_client_slots(self.max_transfers, self.max_transfers_per_client)
        self.trusted = trusted_networks(self.trusted_proxies)


CONFIG_KEY = web.AppKey("config", ServeConfig)


def cache_control(suffix: str, cfg: ServeConfig) -> str:
    if suffix in MUTABLE_SUFFIXES:
        return f"public, max-age={cfg.manifest_max_age}, must-revalidate"
    return f"public, max-age={cfg.segment_max_age}, immutable"


def response_headers(cfg: ServeConfig) -> dict[str, dict[str, str]]:
    """Per served extension, the headers every response for such a file carries."""
    return {suffix: {"Content-Type": content_type, "Cache-Control": cache_control(suffix, cfg), **CORS_HEADERS}
            for suffix, content_type in CONTENT_TYPES.items()}
