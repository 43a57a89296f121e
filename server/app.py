"""`stgs serve ROOT`: an aiohttp service for the DASH trees `stgs pack` writes.

Files are sent zero-copy (sendfile): plain GETs by our WholeFileResponse,
anything with Range or conditions by aiohttp's FileResponse (206/416, ETag and
Last-Modified with 304), with the DASH content types, cache
lifetimes (segments immutable, manifests short), CORS for browser players and
Prometheus metrics. Only files with a known extension, inside ROOT after
resolving symlinks, and not hidden are served; anything else is 404.

Per request the Python work is what limits throughput (docs/BENCHMARKS.md), so
`stgs serve` runs the app with SceneRunner, which answers plain whole-file
GET/HEADs before aiohttp's router and middleware (WholeFileFastPath); the
file's stat/open run on the event loop rather than through a thread hop; and
`workers` processes can share the port (SO_REUSEPORT), their metrics summed
through prometheus_client's multiprocess mode.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ctypes
import dataclasses
import functools
import json
import logging
import math
import multiprocessing
import multiprocessing.synchronize
import os
import signal
import socket
import stat
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from aiohttp import web
from aiohttp.abc import AbstractAccessLogger, AbstractStreamWriter
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest, multiprocess
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
HEADERS_KEY = web.AppKey("headers", dict)


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
    workers: int = 1
    """Server processes sharing the port (SO_REUSEPORT: the kernel spreads connections); /metrics sums them all."""
    io_threads: int | None = 0
    """Threads for each file's stat/open/close: 0 does them on the event loop (microseconds on a local disk,
    far less than a hop to a thread), N uses N threads (slow network storage), None leaves the loop's
    default executor alone (a server sharing its loop with other code, like the demo's player)."""


class InlineExecutor(ThreadPoolExecutor):
    """Runs each call at once on the calling thread (asyncio wants its default executor to be a thread pool)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed to the awaiting coroutine, as a pool would
            future.set_exception(exc)
        return future


MULTIPROCESS_ENV = "PROMETHEUS_MULTIPROC_DIR"
"""Set (to a folder shared by the workers) when several processes serve: prometheus_client then keeps every
value in a file there, and /metrics reads them all."""


class Metrics:
    """Prometheus metrics of one app (own registry, so tests can run several apps).

    Each update of a prometheus_client metric takes a lock (and, with several workers, writes an mmap'ed
    file): ~13 µs per request for the five a request made. Requests therefore count into plain integers,
    folded into the Prometheus metrics by `flush` — before every /metrics answer and every FLUSH_SECONDS
    (so with several workers the others' figures lag by at most that). The latency histogram is observed
    per request: prometheus_client has no bulk update for it.
    """

    FLUSH_SECONDS = 1.0

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("stgs_http_requests", "HTTP requests", ["method", "status"],
                                registry=self.registry)
        self.bytes = Counter("stgs_http_sent_bytes", "Body bytes sent", registry=self.registry)
        self.in_flight = Gauge("stgs_http_in_flight", "Requests being handled", registry=self.registry,
                               multiprocess_mode="livesum")
        self.latency = Histogram("stgs_http_request_seconds", "Request handling time including the transfer",
                                 buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
                                 registry=self.registry)
        self.handling = 0
        """Requests being handled now (the gauge gets it at each flush)."""
        self._answered: collections.Counter[tuple[str, int]] = collections.Counter()
        self._sent = 0

    def answered(self, method: str, status: int, seconds: float, body_bytes: int) -> None:
        """One request answered: its status, handling time (the transfer included) and body bytes."""
        self._answered[(method, status)] += 1
        self.latency.observe(seconds)
        self._sent += body_bytes

    def flush(self) -> None:
        """Fold the counts kept since the last flush into the Prometheus metrics."""
        answered, self._answered = self._answered, collections.Counter()
        for (method, status), count in answered.items():
            self.requests.labels(method, str(status)).inc(count)
        sent, self._sent = self._sent, 0
        if sent:
            self.bytes.inc(sent)
        self.in_flight.set(self.handling)

    def exposition(self) -> bytes:
        """The text format: this process's values, or with several workers the sum over all of them."""
        self.flush()
        if MULTIPROCESS_ENV not in os.environ:
            return generate_latest(self.registry)
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry)


async def flush_metrics(app: web.Application) -> AsyncIterator[None]:
    """Cleanup context: flushes the app's metrics every Metrics.FLUSH_SECONDS and once more at shutdown."""
    metrics: Metrics = app[METRICS_KEY]

    async def periodically() -> None:
        while True:
            await asyncio.sleep(metrics.FLUSH_SECONDS)
            metrics.flush()

    task = asyncio.create_task(periodically())
    yield
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    metrics.flush()


class JsonAccessLogger(AbstractAccessLogger):
    """One JSON object per request: time, client, method, path, range, status, body bytes, seconds."""

    @property
    def enabled(self) -> bool:
        return self.logger.isEnabledFor(logging.INFO)

    def log(self, request: web.BaseRequest, response: web.StreamResponse, time_s: float) -> None:
        self.logger.info(json.dumps({
            "ts": round(time.time(), 3), "remote": request.remote, "method": request.method,
            "path": request.path, "range": request.headers.get("Range"), "status": response.status,
            "bytes": body_bytes(request, response), "seconds": round(time_s, 6)}))


def body_bytes(request: web.BaseRequest, response: web.StreamResponse) -> int:
    """Body bytes a response carries (a file's go out by sendfile, past the writer's own count)."""
    if request.method == "HEAD":
        return 0
    if isinstance(response, (SlottedFileResponse, WholeFileResponse)):
        return (response.content_length or 0) if response.status in (200, 206) else 0
    body = getattr(response, "body", None)
    return len(body) if isinstance(body, bytes) else 0


def servable_parts(url_path: str) -> list[str] | None:
    """The path components of a URL path that may name a served file, or None: no NUL or backslash, no ".",
    ".." or hidden names, and a served extension. What the file system then says is the caller's part."""
    if "\x00" in url_path or "\\" in url_path:
        return None
    parts = [p for p in url_path.split("/") if p]
    if not parts or any(p[0] == "." for p in parts):  # ".", ".." and hidden names
        return None
    if os.path.splitext(parts[-1])[1] not in CONTENT_TYPES:
        return None
    return parts


def resolve_path(root: Path, url_path: str) -> str | None:
    """The file under root that url_path names, or None (outside root, hidden, unknown type, missing).

    `root` must already be resolved. Without symlinks below root, one lstat per component decides; a symlink
    anywhere sends the path through realpath and a containment check. Plain strings, not pathlib: this
    runs for every request, and its Python is a measurable share of one.
    """
    parts = servable_parts(url_path)
    if parts is None:
        return None
    current = str(root).rstrip("/")
    for part in parts:
        current += "/" + part
        try:
            mode = os.lstat(current).st_mode
        except OSError:
            return None
        if stat.S_ISLNK(mode):
            return resolve_symlinked(root, root.joinpath(*parts))
    return current if stat.S_ISREG(mode) else None


def resolve_symlinked(root: Path, candidate: Path) -> str | None:
    try:
        real = candidate.resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    if not real.is_relative_to(root) or not real.is_file() or real.suffix not in CONTENT_TYPES:
        return None  # a link may only lead to a servable file inside root
    return str(real)


def cache_control(suffix: str, cfg: ServeConfig) -> str:
    if suffix in MUTABLE_SUFFIXES:
        return f"public, max-age={cfg.manifest_max_age}, must-revalidate"
    return f"public, max-age={cfg.segment_max_age}, immutable"


def response_headers(cfg: ServeConfig) -> dict[str, dict[str, str]]:
    """Per served extension, the headers every response for such a file carries."""
    return {suffix: {"Content-Type": content_type, "Cache-Control": cache_control(suffix, cfg), **CORS_HEADERS}
            for suffix, content_type in CONTENT_TYPES.items()}


async def counted_transfer(app: web.Application, request: web.BaseRequest, response: web.StreamResponse,
                           send: Callable[[web.BaseRequest], Awaitable[AbstractStreamWriter | None]],
                           ) -> AbstractStreamWriter | None:
    """Run a file response's `send` inside one of the app's transfer slots; report it to the metrics (status,
    time including the transfer, body bytes) once it ends, also when the client hung up."""
    metrics: Metrics = app[METRICS_KEY]
    start = time.perf_counter()
    metrics.handling += 1
    try:
        async with app[SLOTS_KEY]:
            return await send(request)
    finally:
        metrics.handling -= 1
        metrics.answered(request.method, response.status, time.perf_counter() - start, body_bytes(request, response))


class SlottedFileResponse(web.FileResponse):
    """aiohttp's FileResponse (Range, conditions), sent inside a transfer slot and reported to the metrics."""

    def __init__(self, app: web.Application, path: str, headers: dict[str, str]):
        super().__init__(path, headers=headers)
        self._app = app

    async def prepare(self, request: web.BaseRequest) -> AbstractStreamWriter | None:
        return await counted_transfer(self._app, request, self, super().prepare)


CONDITIONAL_HEADERS = ("Range", "If-Range", "If-None-Match", "If-Modified-Since", "If-Match",
                       "If-Unmodified-Since")
"""Requests with any of these go through aiohttp's FileResponse (206/416, 304, 412)."""


class WholeFileResponse(web.StreamResponse):
    """200 with a whole file, for GET/HEAD without Range or conditions: what a player sends for every segment.

    The same answer FileResponse gives such a request (same ETag, Last-Modified, Accept-Ranges), with less
    Python per request, which is what limits this server (docs/BENCHMARKS.md): the file is opened and stat'ed
    once, and the body goes out by os.sendfile straight on the socket, in one call when the socket's buffer
    takes it; asyncio's loop.sendfile sends whatever is left.
    """

    def __init__(self, app: web.Application, path: str, headers: dict[str, str],
                 opened: tuple[int, os.stat_result] | None = None):
        super().__init__(headers=headers)
        self._app = app
        self._path = path
        self._opened = opened  # (descriptor, stat) of the file the fast path opened; this response closes it

    async def prepare(self, request: web.BaseRequest) -> AbstractStreamWriter | None:
        try:
            return await counted_transfer(self._app, request, self, self._send)
        finally:
            if self._opened is not None:  # never sent (cancelled while waiting for a slot)
                os.close(self._opened[0])
                self._opened = None

    async def _send(self, request: web.BaseRequest) -> AbstractStreamWriter | None:
        try:
            if self._opened is not None:
                (fd, st), self._opened = self._opened, None
            elif self._app[CONFIG_KEY].io_threads == 0:
                fd, st = open_and_stat(self._path)
            else:  # slow storage: keep the syscalls off the event loop, as FileResponse does
                fd, st = await asyncio.get_running_loop().run_in_executor(None, open_and_stat, self._path)
        except OSError:  # gone or unreadable since resolve_path looked
            self.set_status(404)
            return await super().prepare(request)
        try:
            self.headers.update(file_validators(st.st_size, st.st_mtime_ns, st.st_mtime))
            writer = await super().prepare(request)
            if request.method != "HEAD" and st.st_size:
                await send_file_body(request, fd, st.st_size)
                await super().write_eof()
            return writer
        finally:
            os.close(fd)


@functools.lru_cache(maxsize=4096)
def file_validators(size: int, mtime_ns: int, mtime: float) -> dict[str, str]:
    """Content-Length, ETag, Last-Modified and Accept-Ranges of a whole file, as aiohttp's FileResponse writes
    them (its property setters validate and format on every call; a segment's values repeat on every request)."""
    modified = time.strftime("%a, %d %b %Y %H:%M:%S GMT", time.gmtime(math.ceil(mtime)))
    return {"Content-Length": str(size), "ETag": f'"{mtime_ns:x}-{size:x}"', "Last-Modified": modified,
            "Accept-Ranges": "bytes"}


def open_and_stat(path: str) -> tuple[int, os.stat_result]:
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        return fd, os.fstat(fd)
    except OSError:
        os.close(fd)
        raise


async def send_file_body(request: web.BaseRequest, fd: int, size: int) -> None:
    transport = request.transport
    if transport is None or transport.is_closing():
        raise ConnectionResetError("connection lost")
    sent = 0
    if transport.get_write_buffer_size() == 0:  # the headers are out: the socket is ours until the body is
        sock = transport.get_extra_info("socket")
        try:
            while sent < size:
                n = os.sendfile(sock.fileno(), fd, sent, size - sent)
                if n == 0:
                    break
                sent += n
        except BlockingIOError:
            pass
        except OSError as exc:  # peer gone (EPIPE, ECONNRESET)
            raise ConnectionResetError(str(exc)) from exc
    if sent < size:
        with open(fd, "rb", closefd=False) as f:
            await asyncio.get_running_loop().sendfile(transport, f, sent, size - sent)


async def serve_file(request: web.Request) -> web.StreamResponse:
    app = request.app
    path = resolve_path(app[ROOT_KEY], request.path)
    if path is None:
        raise web.HTTPNotFound()
    headers = app[HEADERS_KEY][os.path.splitext(path)[1]]
    if any(name in request.headers for name in CONDITIONAL_HEADERS):
        return SlottedFileResponse(app, path, headers)
    return WholeFileResponse(app, path, headers)


class BeneathOpener:
    """Opens files below one folder with openat2(2) and RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS: one syscall in which
    the kernel refuses `..`, absolute paths and every symlink on the way (EXDEV, ELOOP). Nothing can swap a
    component for a symlink between a check and the open, as it could between resolve_path's lstats and a
    later open. Linux 5.6+; `for_root` gives None where the kernel (or a seccomp filter) lacks it."""

    SYS_OPENAT2 = 437  # one number on every Linux architecture
    RESOLVE = 0x02 | 0x04 | 0x08  # RESOLVE_NO_MAGICLINKS | RESOLVE_NO_SYMLINKS | RESOLVE_BENEATH

    class OpenHow(ctypes.Structure):
        _fields_ = [("flags", ctypes.c_uint64), ("mode", ctypes.c_uint64), ("resolve", ctypes.c_uint64)]

    def __init__(self, root_fd: int):
        libc = ctypes.CDLL(None, use_errno=True)
        self._syscall = libc.syscall
        self._syscall.restype = ctypes.c_long
        self._syscall.argtypes = [ctypes.c_long, ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p, ctypes.c_size_t]
        self._how = self.OpenHow(os.O_RDONLY | os.O_CLOEXEC, 0, self.RESOLVE)
        self._how_address = ctypes.addressof(self._how)
        self._how_size = ctypes.sizeof(self._how)
        self.root_fd = root_fd

    @classmethod
    def for_root(cls, root: Path) -> BeneathOpener | None:
        if not sys.platform.startswith("linux"):
            return None
        opener = cls(os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC))
        try:
            os.close(opener.open("."))
        except OSError:  # ENOSYS: kernel before 5.6; EPERM: a seccomp profile that forbids it
            opener.close()
            return None
        return opener

    def open(self, relative: str) -> int:
        """A read-only descriptor of root/relative; OSError if missing, outside root or reached through a symlink."""
        fd = self._syscall(self.SYS_OPENAT2, self.root_fd, os.fsencode(relative), self._how_address, self._how_size)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err), relative)
        return fd

    def close(self) -> None:
        os.close(self.root_fd)


class WholeFileFastPath:
    """The server's request handler in front of the app's: whole-file GET/HEADs of servable files, what a player
    sends for every segment, are answered here, past aiohttp's router and middleware (a fifth of the server's
    CPU per request, docs/BENCHMARKS.md); every other request goes on to the app. The answer is the one the
    app's serve_file route gives (same WholeFileResponse), so only the app's own middleware is skipped, and it
    only counts what WholeFileResponse reports itself.

    With an `opener` (openat2) the file is opened here, in one syscall that also keeps the path inside ROOT; a
    path it refuses (missing, a symlink on the way) goes to the app, whose route answers 404 or follows a symlink
    that stays inside ROOT. Without one (old kernels, or io_threads for slow storage) resolve_path checks it."""

    def __init__(self, app: web.Application, app_handler: Callable[[web.BaseRequest], Awaitable[web.StreamResponse]],
                 opener: BeneathOpener | None):
        self._app = app
        self._app_handler = app_handler
        self._root = app[ROOT_KEY]
        self._headers = app[HEADERS_KEY]
        self._opener = opener

    async def __call__(self, request: web.BaseRequest) -> web.StreamResponse:
        if request.method in ("GET", "HEAD") and not any(name in request.headers for name in CONDITIONAL_HEADERS):
            response = self._whole_file(request.path)
            if response is not None:
                return response
        return await self._app_handler(request)

    def _whole_file(self, url_path: str) -> WholeFileResponse | None:
        if self._opener is None:
            path = resolve_path(self._root, url_path)
            if path is None:
                return None
            return WholeFileResponse(self._app, path, self._headers[os.path.splitext(path)[1]])
        parts = servable_parts(url_path)
        if parts is None:
            return None
        relative = "/".join(parts)
        try:
            fd = self._opener.open(relative)
        except OSError:  # missing, or a symlink on the way: the app's route answers
            return None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            return None
        return WholeFileResponse(self._app, f"{self._root}/{relative}", self._headers[os.path.splitext(relative)[1]],
                                 (fd, st))


class SceneRunner(web.AppRunner):
    """The AppRunner of a build_app app with WholeFileFastPath in front of the app: how `stgs serve` runs."""

    _opener: BeneathOpener | None = None

    async def setup(self) -> None:
        await super().setup()
        server = self.server
        assert server is not None
        on_the_loop = self.app[CONFIG_KEY].io_threads == 0
        self._opener = BeneathOpener.for_root(self.app[ROOT_KEY]) if on_the_loop else None
        server.request_handler = WholeFileFastPath(self.app, server.request_handler, self._opener)

    async def cleanup(self) -> None:
        await super().cleanup()
        if self._opener is not None:
            self._opener.close()
            self._opener = None


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
    body = request.app[METRICS_KEY].exposition()
    return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST, "Cache-Control": "no-store"})


@web.middleware
async def observe(request: web.Request, handler) -> web.StreamResponse:
    """Count requests by status; file responses report themselves once their transfer ends (it happens later)."""
    m: Metrics = request.app[METRICS_KEY]
    start = time.perf_counter()
    m.handling += 1
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
        m.handling -= 1
        if not isinstance(response, (SlottedFileResponse, WholeFileResponse)):
            m.answered(request.method, status, time.perf_counter() - start,
                       body_bytes(request, response) if response is not None else 0)


def file_io_executor(threads: int):
    """Cleanup context that makes the loop's default executor (aiohttp's file stat/open) inline or a pool."""

    async def context(app: web.Application) -> AsyncIterator[None]:
        executor = InlineExecutor() if threads == 0 else ThreadPoolExecutor(threads, "stgs-file-io")
        asyncio.get_running_loop().set_default_executor(executor)
        yield
        executor.shutdown(wait=False)

    return context


def build_app(cfg: ServeConfig) -> web.Application:
    root = Path(cfg.root).resolve()
    app = web.Application(middlewares=[observe], client_max_size=1024)
    app[ROOT_KEY] = root
    app[CONFIG_KEY] = cfg
    app[METRICS_KEY] = Metrics()
    app[HEADERS_KEY] = response_headers(cfg)

    async def make_slots(app: web.Application) -> None:
        app[SLOTS_KEY] = asyncio.Semaphore(cfg.max_transfers)

    app.on_startup.append(make_slots)
    app.cleanup_ctx.append(flush_metrics)
    if cfg.io_threads is not None:
        app.cleanup_ctx.append(file_io_executor(cfg.io_threads))
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

    For the demo, benchmarks and tests; `middlewares` run before the server's own (e.g. a test-only delay), and
    then every request takes the app's route, the whole-file fast path included.
    """
    app = build_app(ServeConfig(root=root, port=0, access_log=False, io_threads=None))
    for i, middleware in enumerate(middlewares):
        app.middlewares.insert(i, middleware)
    async with on_loopback(app, web.AppRunner if middlewares else SceneRunner) as base:
        yield base


def run(cfg: ServeConfig) -> None:
    """Serve until SIGINT/SIGTERM; in-flight transfers get cfg.shutdown_timeout seconds to finish."""
    if cfg.workers == 1:
        serve_process(cfg)
    else:
        run_workers(cfg)


@contextlib.contextmanager
def reserved_port(host: str, port: int) -> Iterator[int]:
    """Hold (host, port) with SO_REUSEPORT so that port 0 becomes one port every worker then binds too."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
        yield sock.getsockname()[1]  # bound but never listening: the kernel hands it no connections


def run_workers(cfg: ServeConfig) -> None:
    """cfg.workers processes on one port; SIGTERM/SIGINT reach each, which shuts down as a single server does."""
    with tempfile.TemporaryDirectory(prefix="stgs-metrics-") as metrics_dir, \
            reserved_port(cfg.host, cfg.port) as port:
        os.environ[MULTIPROCESS_ENV] = metrics_dir  # inherited by the workers, which import prometheus afresh
        spawn = multiprocessing.get_context("spawn")
        listening = [spawn.Event() for _ in range(cfg.workers)]
        procs = [spawn.Process(target=serve_process, args=(dataclasses.replace(cfg, port=port), event),
                               name=f"stgs-serve-{i}") for i, event in enumerate(listening)]
        stopping = []

        def stop(signum: int, frame: object) -> None:
            stopping.append(signum)
            for proc in procs:
                if proc.pid is not None and proc.is_alive():
                    os.kill(proc.pid, signal.SIGTERM)

        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
        for proc in procs:
            if not stopping:
                proc.start()
        procs = [proc for proc in procs if proc.pid is not None]
        for proc, event in zip(procs, listening, strict=False):
            while not event.wait(0.1) and proc.is_alive():
                pass
        if all(event.is_set() for event in listening):  # announced once every worker takes connections
            print(f"stgs serve: ======== Running on http://{cfg.host}:{port} ({cfg.workers} workers) ========\n"
                  "(Press CTRL+C to quit)", flush=True)
        for proc in procs:
            proc.join()
            multiprocess.mark_process_dead(proc.pid)
        failed = [proc.exitcode for proc in procs if proc.exitcode]
        if failed:
            raise SystemExit(f"stgs serve: {len(failed)} of {len(procs)} workers failed (exit {failed[0]})")


def leave_signals_to_parent() -> None:
    """A worker takes signals from the parent only: its own process group (a terminal's Ctrl-C or a group kill
    would otherwise arrive twice, and a second SIGTERM cuts the graceful shutdown), and SIGTERM if the parent dies."""
    os.setpgid(0, 0)
    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGTERM)
    if os.getppid() != multiprocessing.parent_process().pid:  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


def serve_process(cfg: ServeConfig, listening: multiprocessing.synchronize.Event | None = None) -> None:
    """One server process; a worker of several sets `listening` instead of printing where it listens."""
    if listening is not None:
        leave_signals_to_parent()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    access = logging.getLogger("stgs.access")
    access.setLevel(logging.INFO if cfg.access_log else logging.WARNING)
    if listening is None:
        def announce(msg: str) -> None:
            print(f"stgs serve: {msg}", flush=True)
    else:
        def announce(msg: str) -> None:
            listening.set()
    asyncio.run(serve_until_signalled(cfg, access, announce))


async def serve_until_signalled(cfg: ServeConfig, access: logging.Logger, announce: Callable[[str], None]) -> None:
    """Serve cfg on its address until SIGINT/SIGTERM, then stop listening and give in-flight transfers
    cfg.shutdown_timeout seconds (aiohttp's graceful shutdown, as web.run_app does it)."""
    runner = SceneRunner(build_app(cfg), shutdown_timeout=cfg.shutdown_timeout, keepalive_timeout=cfg.keepalive_timeout,
                         access_log_class=JsonAccessLogger, access_log=access, max_line_size=cfg.max_header_bytes,
                         max_field_size=cfg.max_header_bytes, max_headers=cfg.max_headers)
    await runner.setup()
    try:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, stop.set)
        site = web.TCPSite(runner, cfg.host, cfg.port, reuse_port=cfg.workers > 1 or None)
        await site.start()
        announce(f"======== Running on {site.name} ========\n(Press CTRL+C to quit)")
        await stop.wait()
    finally:
        await runner.cleanup()
