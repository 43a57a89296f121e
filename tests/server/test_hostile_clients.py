"""`stgs serve` against clients and trees that misbehave: files truncated mid-transfer, pipelined requests,
transfers cut short. The real server (its file fast path included) on loopback, raw sockets as the clients."""

from __future__ import annotations

import asyncio
import contextlib
import os
from pathlib import Path

import aiohttp

from stgs.loopback import connect_from, on_loopback
from stgs.server.app import SceneRunner, build_app, loopback
from stgs.server.config import ServeConfig

BIG = 64 << 20


async def _headers(reader: asyncio.StreamReader) -> tuple[int, dict[str, str]]:
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), timeout=10)
    lines = head.decode().split("\r\n")
    status = int(lines[0].split()[1])
    return status, {k.lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:] if ":" in line)}


async def _read_to_eof(reader: asyncio.StreamReader, limit_s: float = 20) -> bytes:
    chunks = []
    async with asyncio.timeout(limit_s):
        while chunk := await reader.read(1 << 20):
            chunks.append(chunk)
    return b"".join(chunks)


async def test_a_file_truncated_mid_transfer_aborts_the_connection(tmp_path: Path):
    """Two pipelined GETs on one keep-alive connection; the first file shrinks to 2 MB while it is being sent.
    The server must close the connection, never let the second response appear inside the first body."""
    scene = tmp_path / "s"
    scene.mkdir()
    big, small = scene / "big.m4s", scene / "small.m4s"
    big.write_bytes(os.urandom(1 << 20) * (BIG >> 20))
    small.write_bytes(b"SECOND-RESPONSE-BODY")
    async with loopback(tmp_path) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        # a small receive buffer: the server cannot run far ahead
        reader, writer = await connect_from(host, host, int(port), rcvbuf=64 << 10)
        writer.write(b"GET /s/big.m4s HTTP/1.1\r\nHost: x\r\n\r\nGET /s/small.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        await writer.drain()
        status, headers = await _headers(reader)
        assert status == 200 and int(headers["content-length"]) == BIG
        first = await reader.readexactly(1 << 20)
        os.truncate(big, 2 << 20)  # in place, as a careless re-pack or a full disk would
        rest = await _read_to_eof(reader)  # ends: the server closed the connection
        writer.close()
    body = first + rest
    assert len(body) < BIG
    assert b"HTTP/1.1 200" not in body and b"SECOND-RESPONSE-BODY" not in body


async def test_metrics_count_the_bytes_sent_of_a_transfer_cut_short(tmp_path: Path):
    scene = tmp_path / "s"
    scene.mkdir()
    (scene / "big.m4s").write_bytes(bytes(BIG))
    async with loopback(tmp_path) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(b"GET /s/big.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        await _headers(reader)
        await reader.readexactly(1 << 20)
        writer.transport.abort()  # the client goes away a megabyte in
        async with aiohttp.ClientSession() as session:
            for _ in range(50):  # the server notices the reset on its next write
                text = await (await session.get(base + "metrics")).text()
                sent = [line for line in text.splitlines() if line.startswith("stgs_http_sent_bytes_total")]
                if sent and float(sent[0].split()[1]) > 0:
                    break
                await asyncio.sleep(0.1)
    total = float(sent[0].split()[1])
    assert (1 << 20) <= total < BIG // 2, total  # what went out, not the 64 MB the headers announced


async def _stalled_reader(host: str, port: int, source: str, path: str) -> asyncio.StreamWriter:
    """A client at `source` that asks for a big segment and reads nothing of it."""
    _, writer = await connect_from(source, host, port, rcvbuf=4096)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
    await writer.drain()
    return writer


def _rss_bytes() -> int:
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")


async def test_a_header_flood_is_cut_at_the_request_head_bound(tmp_path: Path):
    """Header fields each under the per-field limit, never finished: 431 and closed once the head passes the
    bound, instead of half a megabyte held per connection for as long as the client likes."""
    (tmp_path / "s").mkdir()
    app = build_app(ServeConfig(root=tmp_path, port=0, access_log=False, max_head_bytes=16_384))
    async with on_loopback(app, SceneRunner) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(b"GET /s/x.m4s HTTP/1.1\r\nHost: x\r\n")
        field = b"X-Pad: " + b"a" * 8000 + b"\r\n"
        with contextlib.suppress(ConnectionError):
            for _ in range(62):
                writer.write(field)
                await writer.drain()
        status, headers = await _headers(reader)
        assert status == 431 and headers["connection"] == "close"
        assert await _read_to_eof(reader, limit_s=5) == b""
        writer.close()


async def test_header_floods_from_many_connections_leave_the_server_small(tmp_path: Path):
    (tmp_path / "s").mkdir()
    app = build_app(ServeConfig(root=tmp_path, port=0, access_log=False))
    field = b"X-Pad: " + b"a" * 8000 + b"\r\n"

    async def flood(host: str, port: int, source: str) -> None:
        reader, writer = await connect_from(source, host, port)
        writer.write(b"GET / HTTP/1.1\r\nHost: x\r\n")
        with contextlib.suppress(ConnectionError):
            for _ in range(62):
                writer.write(field)
                await writer.drain()
        await _read_to_eof(reader, limit_s=20)
        writer.close()

    async with on_loopback(app, SceneRunner) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        before = _rss_bytes()
        await asyncio.gather(*(flood(host, int(port), f"127.0.{1 + i // 100}.{1 + i % 100}") for i in range(300)))
        grown = _rss_bytes() - before
    assert grown < 48 << 20, f"{grown >> 20} MB"  # unbounded: 300 x 62 x 8 KB = 145 MB


async def test_connections_per_client_are_capped_without_touching_other_clients(tmp_path: Path):
    scene = tmp_path / "s"
    scene.mkdir()
    (scene / "small.m4s").write_bytes(b"x" * 100)
    app = build_app(ServeConfig(root=tmp_path, port=0, access_log=False, max_connections_per_client=4))
    async with on_loopback(app, SceneRunner) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        held = [await connect_from("127.0.0.5", host, int(port)) for _ in range(4)]
        reader, writer = await connect_from("127.0.0.5", host, int(port))
        status, _ = await _headers(reader)
        assert status == 503 and await _read_to_eof(reader, limit_s=5) == b""
        writer.close()
        async with aiohttp.ClientSession() as session:  # another address is served as usual
            assert (await (await session.get(base + "s/small.m4s")).read()) == b"x" * 100
        held[0][1].close()
        await asyncio.sleep(0.2)
        reader, writer = await connect_from("127.0.0.5", host, int(port))  # a freed place can be taken again
        writer.write(b"GET /s/small.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        status, _ = await _headers(reader)
        assert status == 200
        for _, held_writer in [*held[1:], (reader, writer)]:
            held_writer.close()


async def test_a_bad_request_is_answered_without_echo_or_traceback(tmp_path: Path, caplog):
    (tmp_path / "s").mkdir()
    app = build_app(ServeConfig(root=tmp_path, port=0, access_log=False))
    async with on_loopback(app, SceneRunner) as base:
        host, port = base.split("//")[1].rstrip("/").split(":")
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(b"G<script>alert(1)</script>ET / HTTP/1.1\r\nHost: x\r\n\r\n")
        status, _ = await _headers(reader)
        body = await _read_to_eof(reader, limit_s=5)
        writer.close()
    assert status == 400 and body == b"400 Bad Request\n"
    assert not [r for r in caplog.records if r.exc_info], "a bad request logged a traceback"
