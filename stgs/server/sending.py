"""A file body on the socket: os.sendfile while the socket takes bytes, inside a transfer slot when the response
needs one; parked, with no slot, while the socket is full (stgs.server.slots); reset when the client takes
nothing for the send timeout or when the parked transfers are at their cap and this one has made the least
recent progress."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import struct
import time

from aiohttp import web

from stgs.server.slots import TransferSlots


class ShortFileError(ConnectionResetError):
    """The file ended before the span its headers announced (truncated in place during the transfer)."""


class Sender:
    """A transfer's standing with the slots: holding one while it sends (when it needs one), parked while its
    socket takes nothing."""

    def __init__(self, slots: TransferSlots | None = None, client: str = "", parking: TransferSlots | None = None):
        self.slots, self.client, self.parking = slots, client, parking
        self.holding = False
        self.last_progress = time.monotonic()

    async def take_slot(self) -> None:
        if self.slots is not None and not self.holding:
            await self.slots.acquire(self.client)
            self.holding = True

    def give_back(self) -> None:
        if self.holding and self.slots is not None:
            self.slots.release(self.client)
            self.holding = False


async def send_file_body(request: web.BaseRequest, fd: int, offset: int, count: int, progress: list[int],
                         timeout: float, sender: Sender) -> None:
    """Send bytes [offset, offset + count) of the file; `progress[0]` counts what has gone out.

    os.sendfile straight on the socket while it takes bytes, inside the sender's slot; while the socket is full
    the transfer gives its slot back and parks until it is writable again. A client that takes nothing for
    `timeout` seconds has its connection reset (as nginx's send_timeout with reset_timedout_connection), and so
    does a parked transfer cut to make room for another; a file that ends early (truncated while it was being
    sent) has its connection aborted: the body would end short of its Content-Length and the next response on
    the keep-alive connection would be read as the rest of it."""
    transport = request.transport
    if transport is None or transport.is_closing():
        raise ConnectionResetError("connection lost")
    loop = asyncio.get_running_loop()
    if transport.get_write_buffer_size():  # the headers are not out yet: let the transport flush them
        await _flushed(transport, timeout)
    sock = transport.get_extra_info("socket")
    sent, watch = 0, -1
    try:
        while sent < count:
            await sender.take_slot()
            try:
                n = os.sendfile(sock.fileno(), fd, offset + sent, count - sent)
            except BlockingIOError:
                sender.give_back()
                if watch < 0:  # asyncio lets no one else watch a transport's descriptor: watch a duplicate
                    watch = os.dup(sock.fileno())
                if not await _parked(loop, watch, timeout, sender, transport):
                    reset(transport)
                    raise ConnectionResetError(f"the client took nothing for {timeout:g} s") from None
                continue
            except OSError as exc:  # peer gone (EPIPE, ECONNRESET)
                transport.abort()
                raise ConnectionResetError(str(exc)) from exc
            if n == 0:
                transport.abort()
                raise ShortFileError(f"the file ended {count - sent} bytes before the announced span")
            sent += n
            progress[0] = sent
            sender.last_progress = time.monotonic()
    finally:
        sender.give_back()
        if watch >= 0:
            os.close(watch)


def reset(transport: asyncio.Transport) -> None:
    """Abort a connection whose client takes nothing with a reset (SO_LINGER 0, as nginx's
    reset_timedout_connection): a plain close would leave the kernel holding the unsent bytes for a peer that
    never reads them."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()


class ShedError(ConnectionResetError):
    """A parked transfer cut to make room for another (the one with the least recent progress)."""


async def _parked(loop: asyncio.AbstractEventLoop, fd: int, timeout: float, sender: Sender,
                  transport: asyncio.Transport) -> bool:
    """Wait, parked, until the socket behind descriptor `fd` is writable: True, or False after `timeout`
    seconds. Raises ShedError when the slots cut this transfer for another."""
    ready = loop.create_future()

    def cut() -> None:
        reset(transport)
        if not ready.done():
            ready.set_exception(ShedError("cut to make room for another waiting transfer"))

    def writable() -> None:
        if not ready.done():
            ready.set_result(None)

    loop.add_writer(fd, writable)
    if sender.parking is not None:
        sender.parking.park(ready, sender.last_progress, cut)
    try:
        await asyncio.wait_for(ready, timeout)
        return True
    except TimeoutError:
        return False
    finally:
        if sender.parking is not None:
            sender.parking.unpark(ready)
        loop.remove_writer(fd)


async def _flushed(transport: asyncio.WriteTransport, timeout: float) -> None:
    """Wait until the transport has written out what it buffered (making no progress for `timeout`: abort)."""
    left, stalled = transport.get_write_buffer_size(), 0.0
    while left:
        await asyncio.sleep(0.01)
        now = transport.get_write_buffer_size()
        stalled = 0.0 if now < left else stalled + 0.01
        if stalled >= timeout or transport.is_closing():
            transport.abort()
            raise ConnectionResetError("the client took nothing while the headers were sent")
        left = now
