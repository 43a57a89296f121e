"""`stgs serve ROOT`: an aiohttp service for the DASH trees `stgs pack` writes.

Files are sent with aiohttp's FileResponse (sendfile, zero-copy; Range with
206/416, ETag and Last-Modified with 304), with the DASH content types, cache
lifetimes (segments immutable, manifests short), CORS for browser players and
Prometheus metrics. Only files with a known extension, inside ROOT after
resolving symlinks, and not hidden are served; anything else is 404.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from aiohttp import web
from aiohttp.abc import AbstractAccessLogger
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from stgs.loopback import on_loopback
from stgs.mpd import (
    FEATURE_SCHEME,
    KEYFRAME_EXTENSION,
    KEYFRAME_MIME_TYPE,
    KEYFRAME_SCHEME,
    MPDError,
    parse_mpd,
)
from stgs.tree import MANIFEST

CONTENT_TYPES = {
    ".mpd": "application/dash+xml",
    ".mp4": "video/mp4",
    ".m4s": "video/iso.segment",
    KEYFRAME_EXTENSION: KEYFRAME_MIME_TYPE,
    ".json": "application/json",
}
"""The only files served, by extension."""
MUTABLE_SUFFIXES = (".mpd", ".json")
"""Mutable documents: short cache lifetime. Everything else is an immutable segment."""
CORS_HEADERS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Expose-Headers": "Content-Length, Content-Range, ETag, Last-Modified, Accept-Ranges",
}
ROOT_KEY = web.AppKey("root", Path)
CONFIG_KEY = web.AppKey("config", object)
METRICS_KEY = web.AppKey("metrics", object)
SLOTS_KEY = web.AppKey("slots", asyncio.Semaphore)


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
    """File transfers in flight at once; further requests wait for a slot."""
    keepalive_timeout: float = 15.0
    """Seconds an idle keep-alive connection stays open."""
    max_header_bytes: int = 8190
    """Longest request line / header field accepted (longer: 400)."""
    max_headers: int = 64
    """Most header fields per request."""
    shutdown_timeout: float = 10.0
    """On SIGTERM, seconds in-flight transfers get to finish before they are cut."""
    manifest_max_age: int = 2
    """Cache-Control max-age of MPDs and stats (seconds)."""
    segment_max_age: int = 31_536_000
    """Cache-Control max-age of segments (they never change under one URL)."""
    access_log: bool = True
    """Write one JSON line per request to stderr."""


class Metrics:
    """Prometheus metrics of one app (own registry, so tests can run several apps)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("stgs_http_requests", "HTTP requests", ["method", "status"],
                                registry=self.registry)
        self.bytes = Counter("stgs_http_sent_bytes", "Body bytes sent", registry=self.registry)
        self.in_flight = Gauge("stgs_http_in_flight", "Requests being handled", registry=self.registry)
        self.latency = Histogram("stgs_http_request_seconds", "Request handling time including the transfer",
                                 buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
                                 registry=self.registry)


class JsonAccessLogger(AbstractAccessLogger):
    """One JSON object per request: time, client, method, path, status, bytes, seconds."""

    def log(self, request: web.BaseRequest, response: web.StreamResponse, time_s: float) -> None:
        self.logger.info(json.dumps({
            "ts": round(time.time(), 3), "remote": request.remote, "method": request.method,
            "path": request.path, "range": request.headers.get("Range"), "status": response.status,
            "bytes": response.body_length, "seconds": round(time_s, 6)}))


def resolve_path(root: Path, url_path: str) -> Path | None:
    """The file under root that url_path names, or None (outside root, hidden, unknown type, missing)."""
    if "\x00" in url_path or "\\" in url_path:
        return None
    parts = [p for p in url_path.split("/") if p]
    if any(p in (".", "..") or p.startswith(".") for p in parts):
        return None
    if not parts or Path(parts[-1]).suffix not in CONTENT_TYPES:
        return None
    candidate = root.joinpath(*parts)
    try:
        real = candidate.resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    if not real.is_relative_to(root) or not real.is_file():
        return None
    return real


def cache_control(path: Path, cfg: ServeConfig) -> str:
    if path.suffix in MUTABLE_SUFFIXES:
        return f"public, max-age={cfg.manifest_max_age}, must-revalidate"
    return f"public, max-age={cfg.segment_max_age}, immutable"


class SlottedFileResponse(web.FileResponse):
    """A FileResponse that sends inside one of the app's transfer slots and reports to the metrics."""

    async def prepare(self, request: web.BaseRequest):
        app = request.match_info.current_app
        start = time.perf_counter()
        async with app[SLOTS_KEY]:
            writer = await super().prepare(request)
        m: Metrics = app[METRICS_KEY]
        m.latency.observe(time.perf_counter() - start)
        if request.method == "GET" and self.status in (200, 206):
            m.bytes.inc(self.content_length or 0)
        return writer


async def serve_file(request: web.Request) -> web.StreamResponse:
    root, cfg = request.app[ROOT_KEY], request.app[CONFIG_KEY]
    path = resolve_path(root, request.path)
    if path is None:
        raise web.HTTPNotFound()
    headers = {"Content-Type": CONTENT_TYPES[path.suffix], "Cache-Control": cache_control(path, cfg),
               **CORS_HEADERS}
    return SlottedFileResponse(path, headers=headers)


async def preflight(request: web.Request) -> web.Response:
    return web.Response(status=204, headers={
        **CORS_HEADERS, "Access-Control-Allow-Methods": "GET, HEAD, OPTIONS",
        "Access-Control-Allow-Headers": "Range, If-None-Match, If-Modified-Since",
        "Access-Control-Max-Age": "86400"})


def scene_summary(name: str, manifest: Path) -> dict:
    mpd = parse_mpd(manifest.read_bytes())
    video = mpd.adaptation_set(FEATURE_SCHEME)
    keyframes = mpd.adaptation_set(KEYFRAME_SCHEME)
    seconds = video.segment_template.seconds
    prefix = "" if name == "." else f"{name}/"
    return {"name": name, "manifest": f"/{prefix}manifest.mpd", "duration": mpd.duration,
            "gops": round(mpd.duration / seconds), "gop_seconds": seconds,
            "keyframe_bandwidth": keyframes.representations[0].bandwidth,
            "ladder": [{"id": r.id, "bandwidth": r.bandwidth, "codecs": r.codecs} for r in video.representations]}


def catalogue(root: Path) -> list[dict]:
    """Every packaged scene at root or one folder below, skipping unreadable manifests."""
    candidates = [(".", root / MANIFEST)]
    candidates += [(d.name, d / MANIFEST) for d in sorted(root.iterdir())
                   if d.is_dir() and not d.name.startswith(".")]
    scenes = []
    for name, manifest in candidates:
        if manifest.is_file():
            try:
                scenes.append(scene_summary(name, manifest))
            except (MPDError, OSError, IndexError, ZeroDivisionError):
                logging.getLogger("stgs.server").warning("skipping %s: not a StreamSTGS manifest", manifest)
    return scenes


async def scenes(request: web.Request) -> web.Response:
    data = await asyncio.to_thread(catalogue, request.app[ROOT_KEY])
    return web.json_response({"scenes": data}, headers={"Cache-Control": "no-cache", **CORS_HEADERS})


async def healthz(request: web.Request) -> web.Response:
    return web.json_response({"status": "ok"}, headers={"Cache-Control": "no-store"})


async def metrics(request: web.Request) -> web.Response:
    body = generate_latest(request.app[METRICS_KEY].registry)
    return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST, "Cache-Control": "no-store"})


@web.middleware
async def observe(request: web.Request, handler) -> web.StreamResponse:
    """Count requests by status; files report their transfer time and bytes themselves (it happens later)."""
    m: Metrics = request.app[METRICS_KEY]
    start = time.perf_counter()
    m.in_flight.inc()
    status = 500
    response = None
    try:
        response = await handler(request)
        status = response.status
        return response
    except web.HTTPException as exc:
        status = exc.status
        raise
    finally:
        m.in_flight.dec()
        m.requests.labels(request.method, str(status)).inc()
        if not isinstance(response, SlottedFileResponse):
            m.latency.observe(time.perf_counter() - start)
            body = getattr(response, "body", None)
            m.bytes.inc(len(body) if isinstance(body, bytes) else 0)


def build_app(cfg: ServeConfig) -> web.Application:
    root = Path(cfg.root).resolve()
    app = web.Application(middlewares=[observe], client_max_size=1024)
    app[ROOT_KEY] = root
    app[CONFIG_KEY] = cfg
    app[METRICS_KEY] = Metrics()

    async def make_slots(app: web.Application) -> None:
        app[SLOTS_KEY] = asyncio.Semaphore(cfg.max_transfers)

    app.on_startup.append(make_slots)
    app.router.add_get("/healthz", healthz)
    app.router.add_get("/metrics", metrics)
    app.router.add_get("/scenes", scenes)
    app.router.add_get("/", scenes)
    app.router.add_route("OPTIONS", "/{tail:.*}", preflight)
    app.router.add_get("/{tail:.*}", serve_file)  # also answers HEAD
    return app


@contextlib.asynccontextmanager
async def loopback(root: Path, middlewares: tuple = ()) -> AsyncIterator[str]:
    """Serve `root` on a free loopback port inside the running event loop; yields the base URL (ends in /).

    For the demo, benchmarks and tests; `middlewares` run before the server's own (e.g. a test-only delay).
    """
    app = build_app(ServeConfig(root=root, port=0, access_log=False))
    for i, middleware in enumerate(middlewares):
        app.middlewares.insert(i, middleware)
    async with on_loopback(app) as base:
        yield base


def run(cfg: ServeConfig) -> None:
    """Serve until SIGINT/SIGTERM; in-flight transfers get cfg.shutdown_timeout seconds to finish."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    access = logging.getLogger("stgs.access")
    access.setLevel(logging.INFO if cfg.access_log else logging.WARNING)
    web.run_app(build_app(cfg), host=cfg.host, port=cfg.port, shutdown_timeout=cfg.shutdown_timeout,
                keepalive_timeout=cfg.keepalive_timeout, access_log_class=JsonAccessLogger,
                access_log=access, max_line_size=cfg.max_header_bytes, max_field_size=cfg.max_header_bytes,
                max_headers=cfg.max_headers, print=lambda msg: print(f"stgs serve: {msg}", flush=True))
