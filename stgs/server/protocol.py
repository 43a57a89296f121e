"""The connection layer of `stgs serve`: aiohttp's Server and RequestHandler with guards added.

- Connections per client: a peer address holds at most `per_client` open connections; one more is answered
  503 and closed at once (as nginx's limit_conn does), so one host cannot pin the server's memory and fds.
- Request-head bytes: the request line and all header fields of one request together are bounded
  (`head_bytes`); aiohttp bounds each field and their count, but 64 fields of 8 KB each, never finished, are
  half a megabyte held per connection. Past the bound the client gets 431 and the connection closes.
- Shutdown takes `timeout` in all: aiohttp waits that long for a request in progress and then as long again
  for it to end once cancelled, which a transfer to a client that reads nothing never does by itself (SIGTERM
  took twice the documented time, longer than `docker stop` waits).
- Bad requests are answered with the status phrase only (never the raw request line echoed back) and logged as
  one debug line without a traceback: a malformed request is the client's fault, not the server's.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any

from aiohttp import web
from aiohttp.web_protocol import RequestHandler


@dataclass(frozen=True)
class ConnectionLimits:
    per_client: int
    """Open connections one peer address may hold (0: no limit)."""
    head_bytes: int
    """Bytes the request line and header fields of one request may take together."""


LINGER_S = 1.0
"""After a refusal, how long the connection's incoming bytes are read and dropped before it is closed: closing
with unread bytes makes the kernel send RST, and the client may then lose the answer."""


def refusal(status: HTTPStatus) -> bytes:
    """A complete response that closes the connection, for answers given outside aiohttp's request cycle."""
    return (f"HTTP/1.1 {status.value} {status.phrase}\r\nContent-Length: 0\r\nConnection: close\r\n"
            "Cache-Control: no-store\r\n\r\n").encode()


class GuardedServer(web.Server):
    """aiohttp's Server (the protocol factory of a site) making GuardedRequestHandlers and counting peers."""

    def __init__(self, handler: Any, *, limits: ConnectionLimits, **kwargs: Any) -> None:
        super().__init__(handler, **kwargs)
        self.limits = limits
        self._peers: dict[RequestHandler, str] = {}
        self._per_peer: dict[str, int] = {}

    @classmethod
    def replacing(cls, server: web.Server, limits: ConnectionLimits) -> GuardedServer:
        """A GuardedServer with everything `server` (as AppRunner made it) was given."""
        return cls(server.request_handler, limits=limits, request_factory=server.request_factory,
                   handler_cancellation=server.handler_cancellation, loop=server._loop, **server._kwargs)

    def __call__(self) -> RequestHandler:
        return GuardedRequestHandler(self, loop=self._loop, **self._kwargs)

    def connection_made(self, handler: RequestHandler, transport: asyncio.Transport) -> None:
        super().connection_made(handler, transport)
        peername = transport.get_extra_info("peername")
        peer = str(peername[0]) if isinstance(peername, tuple) else ""
        self._peers[handler] = peer
        self._per_peer[peer] = self._per_peer.get(peer, 0) + 1
        if self.limits.per_client and self._per_peer[peer] > self.limits.per_client \
                and isinstance(handler, GuardedRequestHandler):
            handler.refuse(HTTPStatus.SERVICE_UNAVAILABLE)

    def connection_lost(self, handler: RequestHandler, exc: BaseException | None = None) -> None:
        super().connection_lost(handler, exc)
        peer = self._peers.pop(handler, None)
        if peer is not None:
            left = self._per_peer[peer] - 1
            if left:
                self._per_peer[peer] = left
            else:
                del self._per_peer[peer]


class GuardedRequestHandler(RequestHandler):
    """aiohttp's per-connection protocol with the request-head bound and quiet 4xx answers."""

    _head_bytes = 0
    _body: Any = None  # the payload of the last request parsed, while its body may still arrive
    _refused = False

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        parsed = self._request_count
        super().data_received(data)
        if self._request_count != parsed:
            self._head_bytes = 0
            self._body = self._messages[-1][1] if self._messages else None
            return
        if self._body is not None and not self._body.is_eof():
            return
        self._head_bytes += len(data)
        manager = self._manager
        if isinstance(manager, GuardedServer) and self._head_bytes > manager.limits.head_bytes:
            self.refuse(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE)

    def refuse(self, status: HTTPStatus) -> None:
        """Answer `status` and close, taking the connection from aiohttp; if a response is mid-way on it, just
        cut it (another answer would land inside that body)."""
        self._refused = True
        transport = self.transport
        idle = self._current_request is None and not self._messages
        self.transport = None  # aiohttp's request loop ends without closing it: the linger below does
        self.force_close()
        if transport is None or transport.is_closing():
            return
        if not idle:
            transport.abort()
            return
        transport.write(refusal(status))
        if transport.can_write_eof():
            transport.write_eof()
        self._loop.call_later(LINGER_S, transport.abort)

    async def shutdown(self, timeout: float | None = 15.0) -> None:
        if timeout is not None and timeout > 0 and self._request_in_progress:
            self._handler_waiter = waiter = self._loop.create_future()
            try:
                await asyncio.wait_for(waiter, timeout)
            except TimeoutError:
                pass
            finally:
                self._handler_waiter = None
        await super().shutdown(0.001)  # cancels what is still running (0 would mean: wait without end)

    def handle_error(self, request: web.BaseRequest, status: int = 500, exc: BaseException | None = None,
                     message: str | None = None) -> web.StreamResponse:
        if status >= 500:
            return super().handle_error(request, status, exc, message)
        self.log_debug("Bad request from %s: %s", request.remote, type(exc).__name__ if exc else status)
        if request.writer.output_size > 0:
            raise ConnectionError("a response is under way: the connection is closed instead")
        phrase = HTTPStatus(status).phrase
        response = web.Response(status=status, text=f"{status} {phrase}\n", headers={"Cache-Control": "no-store"})
        response.force_close()
        return response
