"""File responses: one class (`FileTransfer`) answers every GET/HEAD of a file, whole, ranged or conditional: it
opens and stats the file, lets `decide` pick 200/206/304/412/416 and the span, and only then does I/O (the
body by stgs.server.sending, which holds a transfer slot only while the socket takes bytes), and reports itself
to the metrics. The route handler and the fast path in front of the router both answer with it."""

from __future__ import annotations

import asyncio
import os
import stat
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, TypeGuard

from aiohttp import web
from aiohttp.abc import AbstractStreamWriter

from stgs.server.clients import client_address
from stgs.server.config import CONFIG_KEY, HEADERS_KEY, METRICS_KEY, MUTABLE_SUFFIXES, ROOT_KEY, SLOTS_KEY
from stgs.server.decide import decide
from stgs.server.files import BeneathOpener, open_and_stat, resolve_path, servable_parts
from stgs.server.sending import Sender, send_file_body
from stgs.server.slots import SLOT_FREE_BYTES

if TYPE_CHECKING:
    from stgs.server.metrics import Metrics


def is_file_response(response: web.StreamResponse | None) -> TypeGuard[FileTransfer]:
    """File responses report themselves to the metrics once their transfer ends."""
    return isinstance(response, FileTransfer)


def body_bytes(request: web.BaseRequest, response: web.StreamResponse) -> int:
    """Body bytes a response carries (a file's go out by sendfile, past the writer's own count)."""
    if request.method == "HEAD":
        return 0
    if is_file_response(response):
        return response.body_sent[0]
    body = getattr(response, "body", None)
    return len(body) if isinstance(body, bytes) else 0


async def counted_transfer(app: web.Application, request: web.BaseRequest, response: web.StreamResponse,
                           send: Callable[[web.BaseRequest], Awaitable[AbstractStreamWriter | None]],
                           ) -> AbstractStreamWriter | None:
    """Run a file response's `send`; report it to the metrics (status, time including the transfer, body bytes)
    once it ends, also when the client hung up."""
    metrics: Metrics = app[METRICS_KEY]
    start = time.perf_counter()
    metrics.handling += 1
    try:
        return await send(request)
    finally:
        metrics.handling -= 1
        metrics.answered(request.method, response.status, time.perf_counter() - start, body_bytes(request, response))


def needs_slot(path: str, count: int) -> bool:
    """Whether a body of `count` bytes of `path` is sent inside transfer slots: documents (MPD, JSON) and small
    bodies (init segments) never queue behind segments."""
    return count > SLOT_FREE_BYTES and os.path.splitext(path)[1] not in MUTABLE_SUFFIXES


class FileTransfer(web.StreamResponse):
    """The answer to a GET/HEAD of a servable file; what a player sends for every segment.

    The answer aiohttp's FileResponse gives (same ETag, Last-Modified, Accept-Ranges, ranges and conditions),
    with less Python per request, which is what limits this server (docs/BENCHMARKS.md): the file is opened and
    stat'ed once, and the body goes out by os.sendfile straight on the socket (send_file_body), in one call
    when the socket's buffer takes it.
    """

    def __init__(self, app: web.Application, path: str, headers: dict[str, str],
                 opened: tuple[int, os.stat_result] | None = None):
        super().__init__(headers=headers)
        self._app = app
        self._path = path
        self._opened = opened  # (descriptor, stat) of the file the fast path opened; this response closes it
        self.body_sent = [0]
        """Body bytes sent so far (what the metrics count, also for a transfer cut short)."""
        self.client = ""
        """The address the per-client limits counted (the peer's, or a trusted proxy's forwarded client)."""

    async def prepare(self, request: web.BaseRequest) -> AbstractStreamWriter | None:
        try:
            return await counted_transfer(self._app, request, self, self._send)
        finally:
            if self._opened is not None:  # never sent (cancelled while waiting for a slot)
                os.close(self._opened[0])
                self._opened = None

    async def _send(self, request: web.BaseRequest) -> AbstractStreamWriter | None:
        self.client = client_address(request.remote or "", request.headers, self._app[CONFIG_KEY].trusted)
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
            answer = decide(request, st.st_size, st.st_mtime_ns, st.st_mtime)
            if answer.status != 200:
                self.set_status(answer.status)
            self.headers.update(answer.headers)
            writer = await super().prepare(request)
            if request.method != "HEAD" and answer.count:
                cfg = self._app[CONFIG_KEY]
                slots = self._app[SLOTS_KEY] if needs_slot(self._path, answer.count) else None
                await send_file_body(request, fd, answer.offset, answer.count, self.body_sent, cfg.send_timeout,
                                     Sender(slots, self.client, self._app[SLOTS_KEY]))
                await super().write_eof()
            return writer
        finally:
            os.close(fd)


async def serve_file(request: web.Request) -> web.StreamResponse:
    app = request.app
    path = resolve_path(app[ROOT_KEY], request.path)
    if path is None:
        raise web.HTTPNotFound()
    return FileTransfer(app, path, app[HEADERS_KEY][os.path.splitext(path)[1]])


class FileFastPath:
    """The server's request handler in front of the app's: GET/HEADs of servable files, what a player sends for
    every segment, are answered here, past aiohttp's router and middleware (a fifth of the server's
    CPU per request, docs/BENCHMARKS.md); every other request goes on to the app. The answer is the one the
    app's serve_file route gives (same FileTransfer), so only the app's own middleware is skipped, and it
    only counts what FileTransfer reports itself.

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
        if request.method in ("GET", "HEAD"):
            response = self._file(request.path)
            if response is not None:
                return response
        return await self._app_handler(request)

    def _file(self, url_path: str) -> FileTransfer | None:
        if self._opener is None:
            path = resolve_path(self._root, url_path)
            if path is None:
                return None
            return FileTransfer(self._app, path, self._headers[os.path.splitext(path)[1]])
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
        return FileTransfer(self._app, f"{self._root}/{relative}", self._headers[os.path.splitext(relative)[1]],
                            (fd, st))
