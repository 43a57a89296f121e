"""`stgs serve` when clients that never read outnumber the transfer slots or share an honest viewer's address, and
behind a trusted proxy: the real server (SceneRunner, its fast path included) on loopback, raw sockets with a
4 KB receive buffer as the non-readers."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest

from stgs.errors import FieldError
from stgs.loopback import connect_from, on_loopback
from stgs.server.app import SceneRunner, build_app
from stgs.server.clients import client_address, trusted_networks
from stgs.server.config import SLOTS_KEY, ServeConfig
from stgs.server.metrics import JsonAccessLogger
from stgs.server.slots import TransferSlots, per_client_slots

SEGMENT = 20 << 20
MPD = b'<?xml version="1.0"?><MPD xmlns="urn:mpeg:dash:schema:mpd:2011"/>'


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("slow")
    scene = root / "s"
    scene.mkdir()
    (scene / "big.m4s").write_bytes(os.urandom(1 << 20) * (SEGMENT >> 20))
    (scene / "seg.m4s").write_bytes(os.urandom(2 << 20))
    (scene / "manifest.mpd").write_bytes(MPD)
    return root


async def non_reader(source: str, host: str, port: int, path: str = "/s/big.m4s") -> asyncio.StreamWriter:
    """A client that asks for a big segment and never reads a byte of the answer."""
    _, writer = await connect_from(source, host, port, rcvbuf=4096)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
    await writer.drain()
    return writer


@contextlib.asynccontextmanager
async def server(cfg: ServeConfig, **runner_kwargs):
    app = build_app(cfg)
    async with on_loopback(app, SceneRunner, **runner_kwargs) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        yield app, base, host, int(port)


@pytest.mark.parametrize("sources", [["127.0.0.1"], [f"127.0.0.{i}" for i in range(2, 7)]],
                         ids=["sharing the honest client's address", "on five other addresses"])
async def test_an_honest_client_is_answered_at_once_beside_forty_non_readers(tree, sources):
    """40 non-readers against 8 slots: the MPD within 0.5 s and a 2 MB segment within 1 s (were a blocked
    transfer to keep its slot, the MPD would wait for a non-reader's send timeout, 30 s)."""
    cfg = ServeConfig(root=tree, port=0, access_log=False, max_transfers=8, send_timeout=30)
    async with server(cfg) as (app, base, host, port), aiohttp.ClientSession() as session:
        hogs = [await non_reader(sources[i % len(sources)], host, port) for i in range(40)]
        for _ in range(100):  # every non-reader has filled its socket and parked
            if app[SLOTS_KEY].parked == 40:
                break
            await asyncio.sleep(0.05)
        assert app[SLOTS_KEY].parked == 40
        start = time.perf_counter()
        assert await (await session.get(base + "s/manifest.mpd")).read() == MPD
        mpd_s = time.perf_counter() - start
        start = time.perf_counter()
        body = await (await session.get(base + "s/seg.m4s")).read()
        segment_s = time.perf_counter() - start
        assert len(body) == 2 << 20
        for writer in hogs:
            writer.transport.abort()
    assert mpd_s < 0.5 and segment_s < 1.0, (mpd_s, segment_s)


def raw_non_reader(source: str, host: str, port: int) -> socket.socket:
    """A plain socket that asks for the big segment and never reads; its SO_ERROR shows a reset by the server."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.bind((source, 0))
    sock.settimeout(5)
    sock.connect((host, port))  # loopback: the kernel completes it without the server's accept
    sock.sendall(b"GET /s/big.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
    return sock


def was_reset(sock: socket.socket) -> bool:
    return sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == errno.ECONNRESET


async def test_at_the_waiting_cap_the_transfer_with_the_least_recent_progress_is_cut(tree):
    cfg = ServeConfig(root=tree, port=0, access_log=False, max_transfers=8, max_waiting_transfers=4,
                      send_timeout=30)
    async with server(cfg) as (app, base, host, port), aiohttp.ClientSession() as session:
        slots = app[SLOTS_KEY]
        first = []
        for _ in range(4):  # one after the other: the first parked has the least recent progress
            first.append(raw_non_reader("127.0.0.2", host, port))
            while slots.parked < len(first):
                await asyncio.sleep(0.02)
        health = await session.get(base + "healthz")  # at the cap: a load balancer is told
        assert health.status == 503 and (await health.json())["status"] == "saturated"
        newest = raw_non_reader("127.0.0.3", host, port)
        while slots.shed < 1:
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.2)
        assert slots.shed == 1 and slots.parked == 4
        assert [was_reset(s) for s in [*first, newest]] == [True, False, False, False, False]
        text = await (await session.get(base + "metrics")).text()
        assert "stgs_transfers_waiting 4.0" in text and "stgs_transfers_shed_total 1.0" in text
        for sock in [*first, newest]:
            sock.close()


async def test_slots_bound_each_client_to_its_share_and_tell_saturation():
    """Senders of one client wait for its own slots while another client's go ahead; saturated when every
    server-wide slot is taken and a sender waits."""
    slots = TransferSlots(total=4, per_client=1, max_waiting=8)
    await slots.acquire("a")
    second_a = asyncio.create_task(slots.acquire("a"))
    await asyncio.sleep(0.01)
    assert not second_a.done()  # "a" is at its share
    for client in ("b", "c", "d"):
        await asyncio.wait_for(slots.acquire(client), 1)  # others are not held up by "a"
    assert not slots.saturated
    e = asyncio.create_task(slots.acquire("e"))
    await asyncio.sleep(0.01)
    assert slots.saturated and not e.done()
    slots.release("b")
    await asyncio.wait_for(e, 1)
    slots.release("a")
    await asyncio.wait_for(second_a, 1)
    second_a.cancel()
    for client in ("a", "c", "d", "e"):
        slots.release(client)
    assert not slots.saturated and slots.waiting == 0


def _rss_bytes() -> int:
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")


async def test_parked_transfers_cost_the_server_a_few_kilobytes_each(tree):
    """The memory that bounds waiting transfers (docs/SECURITY.md states ~16 KB each): 300 parked transfers of
    plain-socket non-readers (which keep nothing in this process) grow the process by well under 40 KB each."""
    cfg = ServeConfig(root=tree, port=0, access_log=False, max_transfers=8)
    async with server(cfg) as (app, _base, host, port):
        warm = [raw_non_reader("127.0.2.1", host, port) for _ in range(10)]  # first allocations, not counted
        while app[SLOTS_KEY].parked < len(warm):
            await asyncio.sleep(0.02)
        before = _rss_bytes()
        socks = []
        for i in range(300):
            socks.append(raw_non_reader(f"127.0.2.{2 + i % 50}", host, port))
            await asyncio.sleep(0)  # the server accepts as they come (its listen backlog is finite)
        while app[SLOTS_KEY].parked < len(warm) + len(socks):
            await asyncio.sleep(0.05)
        grown = _rss_bytes() - before
        for sock in [*warm, *socks]:
            sock.close()
    assert grown < 300 * (40 << 10), f"{grown / 300 / 1024:.1f} KB per parked transfer"


def test_a_per_client_cap_above_the_share_is_refused_at_start_up(tree):
    with pytest.raises(FieldError, match="max_transfers_per_client"):
        ServeConfig(root=tree, max_transfers=8, max_transfers_per_client=3)
    assert ServeConfig(root=tree, max_transfers=8).max_transfers_per_client == 2  # the default follows the share
    assert ServeConfig(root=tree).max_transfers_per_client == 32
    assert per_client_slots(2, None) == 1
    result = subprocess.run([sys.executable, "-m", "stgs.cli", "serve", str(tree), "--max-transfers", "8",
                             "--max-transfers-per-client", "3"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("stgs: --max-transfers-per-client 3 ")
    result = subprocess.run([sys.executable, "-m", "stgs.cli", "serve", str(tree), "--trusted-proxy", "10.0.0/33"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--trusted-proxy '10.0.0/33' is not an address or CIDR range" in result.stderr


def test_forwarded_addresses_count_only_from_a_trusted_proxy():
    trusted = trusted_networks(["10.0.0.0/8", "::1"])
    xff = {"X-Forwarded-For": "203.0.113.9, 10.1.2.3"}
    assert client_address("10.9.9.9", xff, trusted) == "203.0.113.9"  # the last untrusted hop
    assert client_address("192.0.2.1", xff, trusted) == "192.0.2.1"  # not a trusted peer: headers ignored
    assert client_address("10.9.9.9", xff, ()) == "10.9.9.9"  # no trusted range: ignored
    assert client_address("10.9.9.9", {"X-Forwarded-For": "198.51.100.1, 203.0.113.9"}, trusted) == "203.0.113.9"
    assert client_address("10.9.9.9", {"X-Forwarded-For": "10.1.1.1"}, trusted) == "10.1.1.1"
    assert client_address("10.9.9.9", {"X-Forwarded-For": "nonsense"}, trusted) == "10.9.9.9"
    forwarded = {"Forwarded": 'for=192.0.2.60;proto=http, for="[2001:db8::7]:4711"',
                 "X-Forwarded-For": "198.51.100.1"}  # Forwarded wins over X-Forwarded-For
    assert client_address("::1", forwarded, trusted) == "2001:db8::7"
    assert client_address("10.0.0.1", {"Forwarded": "for=198.51.100.17:80"}, trusted) == "198.51.100.17"
    with pytest.raises(FieldError, match="trusted_proxies"):
        trusted_networks(["not-a-range"])


async def test_the_access_log_names_the_forwarded_client_only_behind_a_trusted_proxy(tree, caplog):
    logger = logging.getLogger("stgs.test.proxy")
    cfg = ServeConfig(root=tree, port=0, trusted_proxies=("127.0.0.2/32",))
    with caplog.at_level(logging.INFO, logger="stgs.test.proxy"):
        async with server(cfg, access_log_class=JsonAccessLogger, access_log=logger) as (_, _base, host, port):
            for source in ("127.0.0.2", "127.0.0.3"):
                reader, writer = await connect_from(source, host, port)
                writer.write(b"GET /s/manifest.mpd HTTP/1.1\r\nHost: x\r\nX-Forwarded-For: 203.0.113.9\r\n"
                             b"Connection: close\r\n\r\n")
                await writer.drain()
                await reader.read()
                writer.close()
    lines = [json.loads(r.getMessage()) for r in caplog.records if r.name == "stgs.test.proxy"]
    assert [(line["remote"], line.get("client")) for line in lines] == [("127.0.0.2", "203.0.113.9"),
                                                                         ("127.0.0.3", None)]
