"""`stgs serve ROOT`: an aiohttp service for the DASH trees `stgs pack` writes.

Files are sent zero-copy (sendfile) by one response class, FileTransfer,
which decides first (200; 206/416 for ranges; 304/412 for conditions on ETag
and Last-Modified) and does I/O after, with the DASH content types, cache
lifetimes (segments immutable, manifests short), CORS for browser players and
Prometheus metrics. Only files with a known extension, inside ROOT after
resolving symlinks, and not hidden are served; anything else is 404.

Per request the Python work is what limits throughput (docs/BENCHMARKS.md), so
`stgs serve` runs the app with SceneRunner, which answers file GET/HEADs
before aiohttp's router and middleware (FileFastPath); the
file's stat/open run on the event loop rather than through a thread hop; and
`workers` processes can share the port (SO_REUSEPORT), their metrics summed
through prometheus_client's multiprocess mode.

This module is the assembly (routes, cleanup contexts, SceneRunner, the
loopback helper); the parts are in `config`, `files`, `decide`, `responses`,
`sending`, `slots`, `clients`, `metrics`, `catalogue` and `workers`.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from aiohttp import web
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from stgs.loopback import on_loopback
from stgs.server.catalogue import catalogue_thread, scenes
from stgs.server.config import (
    CONFIG_KEY,
    CORS_HEADERS,
    HEADERS_KEY,
    METRICS_KEY,
    ROOT_KEY,
    SLOTS_KEY,
    ServeConfig,
    response_headers,
)
from stgs.server.files import BeneathOpener
from stgs.server.metrics import Metrics, flush_metrics, observe
from stgs.server.player import player_files, player_root, serve_player
from stgs.server.protocol import ConnectionLimits, GuardedServer
from stgs.server.responses import FileFastPath, serve_file
from stgs.server.slots import TransferSlots


class InlineExecutor(ThreadPoolExecutor):
    """Runs each call at once on the calling thread (asyncio wants its default executor to be a thread pool)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed to the awaiting coroutine, as a pool would
            future.set_exception(exc)
        return future


async def preflight(request: web.Request) -> web.Response:
    return web.Response(status=204, headers={
        **CORS_HEADERS, "Access-Control-Allow-Methods": "GET, HEAD, OPTIONS",
        "Access-Control-Allow-Headers": "Range, If-None-Match, If-Modified-Since",
        "Access-Control-Max-Age": "86400"})


async def healthz(request: web.Request) -> web.Response:
    """200 ok, or 503 saturated while every transfer slot is taken and requests wait for one, or while the parked
    transfers are at their cap (stgs.server.slots)."""
    if request.app[SLOTS_KEY].saturated:
        return web.json_response({"status": "saturated"}, status=503, headers={"Cache-Control": "no-store"})
    return web.json_response({"status": "ok"}, headers={"Cache-Control": "no-store"})


async def metrics(request: web.Request) -> web.Response:
    body = request.app[METRICS_KEY].exposition()
    return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST, "Cache-Control": "no-store"})


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
        per_client = cfg.max_transfers_per_client
        assert per_client is not None  # ServeConfig.__post_init__ resolves it
        app[SLOTS_KEY] = TransferSlots(cfg.max_transfers, per_client, cfg.max_waiting_transfers)
        app[METRICS_KEY].slots = app[SLOTS_KEY]

    app.on_startup.append(make_slots)
    app.cleanup_ctx.append(flush_metrics)
    app.cleanup_ctx.append(catalogue_thread)
    app.cleanup_ctx.append(player_files)
    if cfg.io_threads is not None:
        app.cleanup_ctx.append(file_io_executor(cfg.io_threads))
    app.router.add_get("/healthz", healthz)
    app.router.add_get("/metrics", metrics)
    app.router.add_get("/scenes", scenes)
    app.router.add_get("/", scenes)
    app.router.add_get("/player", player_root)
    app.router.add_get("/player/{tail:.*}", serve_player)
    app.router.add_route("OPTIONS", "/{tail:.*}", preflight)
    app.router.add_get("/{tail:.*}", serve_file)  # also answers HEAD
    return app


class SceneRunner(web.AppRunner):
    """The AppRunner of a build_app app with FileFastPath in front of the app and the connection guards of
    stgs.server.protocol (connections per client, request-head bytes): how `stgs serve` runs."""

    _opener: BeneathOpener | None = None

    async def _make_server(self) -> web.Server:
        cfg = self.app[CONFIG_KEY]
        limits = ConnectionLimits(per_client=cfg.max_connections_per_client, head_bytes=cfg.max_head_bytes)
        return GuardedServer.replacing(await super()._make_server(), limits)

    async def setup(self) -> None:
        await super().setup()
        server = self.server
        assert server is not None
        on_the_loop = self.app[CONFIG_KEY].io_threads == 0
        self._opener = BeneathOpener.for_root(self.app[ROOT_KEY]) if on_the_loop else None
        server.request_handler = FileFastPath(self.app, server.request_handler, self._opener)

    async def cleanup(self) -> None:
        await super().cleanup()
        if self._opener is not None:
            self._opener.close()
            self._opener = None


@contextlib.asynccontextmanager
async def loopback(root: Path, middlewares: tuple = ()) -> AsyncIterator[str]:
    """Serve `root` on a free loopback port inside the running event loop; yields the base URL (ends in /).

    For the demo, benchmarks and tests; `middlewares` run before the server's own (e.g. a test-only delay), and
    then every request takes the app's route, the file fast path included.
    """
    app = build_app(ServeConfig(root=root, port=0, access_log=False, io_threads=None))
    for i, middleware in enumerate(middlewares):
        app.middlewares.insert(i, middleware)
    async with on_loopback(app, web.AppRunner if middlewares else SceneRunner) as base:
        yield base

