"""Run an aiohttp application on a free loopback port inside the running event loop, and open raw client
connections to one from a chosen loopback address (tests and benchmarks that play many clients)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator

from aiohttp import web


@contextlib.asynccontextmanager
async def on_loopback(app: web.Application, runner_class: type[web.AppRunner] = web.AppRunner,
                     **runner_kwargs) -> AsyncIterator[str]:
    """Serve `app` on 127.0.0.1 at a free port; yields its base URL (ending in /). `runner_kwargs` go to the
    runner (default: no access log)."""
    runner = runner_class(app, **({"access_log": None} | runner_kwargs))
    await runner.setup()
    try:
        await web.TCPSite(runner, "127.0.0.1", 0).start()
        host, port = runner.addresses[0][:2]
        yield f"http://{host}:{port}/"
    finally:
        await runner.cleanup()


async def connect_from(source: str, host: str, port: int, rcvbuf: int | None = None,
                       timeout: float = 10.0) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """A TCP connection to (host, port) from address `source` (any of 127.0.0.0/8 on loopback: the server sees
    distinct clients), connected without blocking the event loop; `rcvbuf` shrinks the receive buffer (a client
    that reads nothing then stalls the server's send quickly)."""
    sock = socket.socket()
    try:
        if rcvbuf:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.bind((source, 0))
        sock.setblocking(False)
        await asyncio.wait_for(asyncio.get_running_loop().sock_connect(sock, (host, port)), timeout)
    except BaseException:
        sock.close()
        raise
    return await asyncio.open_connection(sock=sock)
