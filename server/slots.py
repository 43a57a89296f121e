"""Transfer slots: how many file transfers run at once, server-wide and per client.

A client (by peer address) holds at most `per_client` slots, so clients that request large segments and never
read them cannot take every slot from the others; each stalled transfer is also cut after the send timeout
(stgs.server.responses.send_file_body). `saturated` is what /healthz reports."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager


class TransferSlots:
    def __init__(self, total: int, per_client: int):
        self.total = asyncio.Semaphore(total)
        self.per_client = per_client
        self._clients: dict[str, tuple[asyncio.Semaphore, list[int]]] = {}
        self.waiting = 0
        """Transfers waiting for a server-wide slot."""

    @asynccontextmanager
    async def hold(self, client: str) -> AsyncIterator[None]:
        """One slot of the server's and one of `client`'s for the duration of the block."""
        own, users = self._clients.setdefault(client, (asyncio.Semaphore(self.per_client), [0]))
        users[0] += 1
        try:
            async with own:
                self.waiting += 1
                try:
                    await self.total.acquire()
                finally:
                    self.waiting -= 1
                try:
                    yield
                finally:
                    self.total.release()
        finally:
            users[0] -= 1
            if users[0] == 0:
                del self._clients[client]

    @property
    def saturated(self) -> bool:
        """Every server-wide slot is taken and transfers wait for one."""
        return self.total.locked() and self.waiting > 0
