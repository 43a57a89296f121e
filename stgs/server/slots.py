"""Transfer slots and parked transfers: what bounds the server's work, and what bounds its waiting.

A **slot** bounds concurrent file I/O. A transfer holds one server-wide slot and one of its client's only while
it sends: when the client's socket takes no more bytes, the transfer gives both back and **parks** until the
socket is writable again (stgs.server.sending), so clients that request large segments and never read them hold
no slot, however many they are and whatever address they share. Small responses (the
documents and any body of at most SLOT_FREE_BYTES: MPDs, stats.json, cameras.json, init segments) take no slot
at all.

What bounds parked transfers is file descriptors and memory: each holds three descriptors (the file, the
socket, a duplicate of the socket to watch it) and about 16 KB, and there are at most `max_waiting` of them.
When one more would park, the parked transfer with the least recent progress is cut (its connection reset),
never the newest request. A transfer that makes no progress for the send timeout is cut too.
"""

from __future__ import annotations

import asyncio
import resource
from collections.abc import Callable

from stgs.errors import FieldError

SLOT_FREE_BYTES = 64 << 10
"""Responses whose body is at most this many bytes are sent without a transfer slot (the socket's buffer takes
them at once)."""

PER_CLIENT_SHARE = 4
"""A client address may hold at most 1/PER_CLIENT_SHARE of the server-wide slots."""

DEFAULT_PER_CLIENT = 32
"""Per-client slots when not set, unless the server-wide share is smaller."""

DESCRIPTORS_PER_PARKED = 3
"""File, socket and the socket's watch duplicate."""

DESCRIPTOR_HEADROOM = 256
"""Descriptors kept for the listening sockets, idle connections, logs and the catalogue."""


def per_client_ceiling(total: int) -> int:
    """The most slots one client address may hold when the server has `total`."""
    return max(1, total // PER_CLIENT_SHARE)


def per_client_slots(total: int, per_client: int | None) -> int:
    """The per-client cap: `per_client`, or the default within the share; a cap above the share is an error."""
    ceiling = per_client_ceiling(total)
    if per_client is None:
        return min(DEFAULT_PER_CLIENT, ceiling)
    if per_client > ceiling:
        raise FieldError("max_transfers_per_client", f"{per_client} is more than one client may hold: at most "
                         f"1/{PER_CLIENT_SHARE} of the {total} server-wide transfers, i.e. {ceiling}")
    return per_client


def reserve_descriptors(max_transfers: int, max_waiting: int) -> None:
    """Raise this process's descriptor limit to fit `max_waiting` parked and `max_transfers` sending transfers
    (up to the hard limit). A hard limit too low for them is an error."""
    needed = DESCRIPTORS_PER_PARKED * max_waiting + 2 * max_transfers + DESCRIPTOR_HEADROOM
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < needed:
        raise FieldError("max_waiting_transfers", f"{max_waiting} parked and {max_transfers} sending transfers "
                         f"need {needed} file descriptors; this process may open {hard} (ulimit -Hn)")
    if soft != resource.RLIM_INFINITY and soft < needed:
        resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


class TransferSlots:
    def __init__(self, total: int, per_client: int, max_waiting: int):
        self.total = asyncio.Semaphore(total)
        self.per_client = per_client
        self.max_waiting = max_waiting
        self._clients: dict[str, tuple[asyncio.Semaphore, list[int]]] = {}
        self._parked: dict[object, tuple[float, Callable[[], None]]] = {}
        self.waiting = 0
        """Transfers waiting for a server-wide slot."""
        self.shed = 0
        """Parked transfers cut to make room for another (saturation)."""

    async def acquire(self, client: str) -> None:
        """One slot of `client`'s and one of the server's (waiting for them in that order)."""
        own, users = self._clients.setdefault(client, (asyncio.Semaphore(self.per_client), [0]))
        users[0] += 1
        try:
            await own.acquire()
        except BaseException:
            self._leave(client, users)
            raise
        self.waiting += 1
        try:
            await self.total.acquire()
        except BaseException:
            own.release()
            self._leave(client, users)
            raise
        finally:
            self.waiting -= 1

    def release(self, client: str) -> None:
        self.total.release()
        own, users = self._clients[client]
        own.release()
        self._leave(client, users)

    def _leave(self, client: str, users: list[int]) -> None:
        users[0] -= 1
        if users[0] == 0:
            del self._clients[client]

    def park(self, key: object, last_progress: float, cut: Callable[[], None]) -> None:
        """Register a transfer waiting for its socket (`cut` aborts it); at the cap, first cut the parked transfer
        with the least recent progress."""
        if len(self._parked) >= self.max_waiting:
            victim = min(self._parked, key=lambda k: self._parked[k][0])
            _, cut_victim = self._parked.pop(victim)
            self.shed += 1
            cut_victim()
        self._parked[key] = (last_progress, cut)

    def unpark(self, key: object) -> None:
        self._parked.pop(key, None)

    @property
    def parked(self) -> int:
        return len(self._parked)

    @property
    def saturated(self) -> bool:
        """Every server-wide slot is taken and transfers wait for one, or the parked transfers are at their cap."""
        return (self.total.locked() and self.waiting > 0) or len(self._parked) >= self.max_waiting
