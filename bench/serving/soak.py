"""Soak: `stgs serve` under honest and hostile clients at once, for minutes (`python -m bench.serving.soak`).

A real `stgs serve` process (default limits) serves a packed scene on loopback. Honest clients, each on its own
loopback address, fetch the manifest and the segments as players do (a request, then a short pause) and time
each request to its last byte. Hostile clients, from other addresses, run at the same time:

- slow readers: ask for the largest segment and never read (reconnect when cut);
- header floods: 62 fields of 8 KB each, never finished;
- slowloris: one header byte every two seconds;
- a connection hog: one address holding 300 idle connections;
- garbage: random bytes as request lines;
- range abuse: a thousand one-byte ranges per request;
- disconnects: a large segment read 64 KB in, then a reset;
- a FIFO inside ROOT asked for again and again.

Every 5 s the server's RSS and open descriptors and the honest clients' latency percentiles are sampled; the
run ends with a table (for docs/BENCHMARKS.md) and a plot of RSS, fds and honest p99 over time.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import aiohttp

from bench.serving.serve import free_port, wait_for
from stgs.loopback import connect_from

SAMPLE_S = 5.0
SEND_TIMEOUT_S = 30.0
"""The server's default --send-timeout."""


def server_memory(pid: int) -> tuple[float, int]:
    """(RSS in MB, open descriptors) of a process."""
    status = Path(f"/proc/{pid}/status").read_text()
    rss_kb = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
    return rss_kb / 1024, len(os.listdir(f"/proc/{pid}/fd"))


async def raw(port: int, source: str, rcvbuf: int | None = None) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await connect_from(source, "127.0.0.1", port, rcvbuf)


class Soak:
    def __init__(self, port: int, paths: list[str], largest: str, seconds: float):
        self.port, self.paths, self.largest = port, paths, largest
        self.end = time.monotonic() + seconds
        self.latencies: list[float] = []
        self.honest = Counter()
        self.hostile = Counter()

    def running(self) -> bool:
        return time.monotonic() < self.end

    async def honest_client(self, i: int) -> None:
        connector = aiohttp.TCPConnector(local_addr=(f"127.0.2.{1 + i}", 0), limit=2)
        timeout = aiohttp.ClientTimeout(total=60)
        rng = random.Random(i)
        async with aiohttp.ClientSession(connector=connector, timeout=timeout) as session:
            while self.running():
                path = rng.choice(self.paths)
                start = time.perf_counter()
                try:
                    async with session.get(f"http://127.0.0.1:{self.port}/{path}") as resp:
                        await resp.read()
                        status = resp.status
                except (aiohttp.ClientError, TimeoutError):
                    self.honest["errors"] += 1
                    continue
                self.latencies.append(time.perf_counter() - start)
                self.honest["5xx" if status >= 500 else "ok" if status == 200 else "other"] += 1
                await asyncio.sleep(0.05)

    async def hostile_loop(self, kind: str, attack, source: str) -> None:
        while self.running():
            try:
                await asyncio.wait_for(attack(source), max(0.1, self.end - time.monotonic()))
                self.hostile[kind] += 1
            except (OSError, TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                self.hostile[kind] += 1
                await asyncio.sleep(0.05)

    async def slow_reader(self, source: str) -> None:
        """Holds a transfer without reading; the client does not notice the server's cut (it reads nothing), so
        it starts over just after the server's send timeout."""
        _, writer = await raw(self.port, source, rcvbuf=4096)
        writer.write(f"GET /{self.largest} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        try:
            await asyncio.sleep(SEND_TIMEOUT_S + 5)
        finally:
            writer.transport.abort()

    async def header_flood(self, source: str) -> None:
        reader, writer = await raw(self.port, source)
        try:
            writer.write(b"GET / HTTP/1.1\r\nHost: x\r\n")
            for _ in range(62):
                writer.write(b"X-Pad: " + b"a" * 8000 + b"\r\n")
                await writer.drain()
                await asyncio.sleep(0.05)
            await reader.read(1024)
        finally:
            writer.transport.abort()

    async def slowloris(self, source: str) -> None:
        _, writer = await raw(self.port, source)
        try:
            for byte in b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 100:
                writer.write(bytes([byte]))
                await writer.drain()
                await asyncio.sleep(2)
        finally:
            writer.transport.abort()

    async def hog(self, source: str) -> None:
        """300 idle connections from one address (the server keeps 128, closes idle ones after its keep-alive
        timeout); starts over every 20 s."""
        held = []
        try:
            for _ in range(300):
                held.append(await raw(self.port, source))
            await asyncio.sleep(20)
        finally:
            for _, writer in held:
                writer.transport.abort()

    async def garbage(self, source: str) -> None:
        reader, writer = await raw(self.port, source)
        try:
            writer.write(os.urandom(random.randint(1, 2000)) + b"\r\n\r\n")
            await reader.read(4096)
        finally:
            writer.transport.abort()
        await asyncio.sleep(0.02)

    async def range_abuse(self, source: str) -> None:
        reader, writer = await raw(self.port, source)
        try:
            ranges = ",".join(f"{i}-{i}" for i in range(1000))
            writer.write(f"GET /{self.largest} HTTP/1.1\r\nHost: x\r\nRange: bytes={ranges}\r\n"
                         "Connection: close\r\n\r\n".encode())
            while await reader.read(1 << 16):
                pass
        finally:
            writer.transport.abort()

    async def disconnect(self, source: str) -> None:
        reader, writer = await raw(self.port, source)
        writer.write(f"GET /{self.largest} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        await reader.readexactly(1 << 16)
        writer.transport.abort()

    async def fifo(self, source: str) -> None:
        reader, writer = await raw(self.port, source)
        try:
            writer.write(b"GET /scene/evil.m4s HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            await reader.read(4096)
        finally:
            writer.transport.abort()
        await asyncio.sleep(0.05)


def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


async def run(port: int, pid: int, paths: list[str], largest: str, seconds: float, honest: int) -> dict:
    soak = Soak(port, paths, largest, seconds)
    attacks = [("slow reader", soak.slow_reader, 40), ("header flood", soak.header_flood, 20),
               ("slowloris", soak.slowloris, 50), ("hog", soak.hog, 1), ("garbage", soak.garbage, 4),
               ("range abuse", soak.range_abuse, 2), ("disconnect", soak.disconnect, 4), ("fifo", soak.fifo, 2)]
    tasks = [asyncio.create_task(soak.honest_client(i)) for i in range(honest)]
    for a, (kind, attack, count) in enumerate(attacks):
        tasks += [asyncio.create_task(soak.hostile_loop(kind, attack, f"127.0.{10 + a}.{1 + i % 4}"))
                  for i in range(count)]
    samples, seen = [], 0
    start = time.monotonic()
    while soak.running():
        await asyncio.sleep(SAMPLE_S)
        rss, fds = server_memory(pid)
        window, seen = soak.latencies[seen:], len(soak.latencies)
        samples.append({"t_s": round(time.monotonic() - start, 1), "rss_mb": round(rss, 1), "fds": fds,
                        "honest_requests": len(window), "p50_ms": _ms(percentile(window, 0.5)),
                        "p99_ms": _ms(percentile(window, 0.99)), "honest": dict(soak.honest),
                        "hostile": dict(soak.hostile)})
        print(json.dumps(samples[-1]), flush=True)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    return {"seconds": seconds, "honest_clients": honest, "samples": samples, "honest": dict(soak.honest),
            "hostile": dict(soak.hostile), "p50_ms": _ms(percentile(soak.latencies, 0.5)),
            "p99_ms": _ms(percentile(soak.latencies, 0.99)), "max_ms": _ms(max(soak.latencies, default=None))}


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1e3, 1)


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [s["t_s"] for s in result["samples"]]
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for ax, key, label in zip(axes, ("rss_mb", "fds", "p99_ms"), ("server RSS (MB)", "server open fds",
                                                                    "honest p99 (ms)"), strict=True):
        ax.plot(t, [s[key] for s in result["samples"]])
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("seconds")
    fig.suptitle("stgs serve under honest and hostile clients (bench/serving/soak.py)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, help="a packed scene (default: the demo preset, packed here)")
    parser.add_argument("--seconds", type=float, default=600.0)
    parser.add_argument("--honest", type=int, default=8, help="honest clients")
    parser.add_argument("--out", type=Path, default=Path("soak.json"))
    parser.add_argument("--plot", type=Path, default=Path("docs/soak.png"))
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="stgs-soak-") as tmp:
        root = Path(tmp) / "root"
        if args.scene is None:
            import dataclasses

            from stgs.packager import PackConfig, pack
            from stgs.synth import PRESETS, synthesize

            synthesize(dataclasses.replace(PRESETS["demo"], fit_steps=20), Path(tmp) / "model", progress=False)
            pack(Path(tmp) / "model", root / "scene", PackConfig(ladder="fixed"), progress=False)
        else:
            shutil.copytree(args.scene, root / "scene")
        os.mkfifo(root / "scene" / "evil.m4s")
        files = sorted(p for p in (root / "scene").rglob("*") if p.is_file() and p.suffix != ".json")
        paths = [str(p.relative_to(root)) for p in files]
        largest = str(max(files, key=lambda p: p.stat().st_size).relative_to(root))
        port = free_port()
        server = subprocess.Popen([sys.executable, "-m", "stgs.cli", "serve", str(root), "--port", str(port),
                                   "--quiet"], stdout=subprocess.DEVNULL)
        try:
            wait_for(port)
            idle = server_memory(server.pid)
            result = asyncio.run(run(port, server.pid, paths, largest, args.seconds, args.honest))
        finally:
            server.terminate()
            server.wait(timeout=30)
    result["idle_rss_mb"], result["idle_fds"] = round(idle[0], 1), idle[1]
    args.out.write_text(json.dumps(result, indent=1))
    plot(result, args.plot)
    rss = [s["rss_mb"] for s in result["samples"]]
    fds = [s["fds"] for s in result["samples"]]
    print(f"| honest requests | errors | 5xx | p50 | p99 | max | RSS idle / peak / end | fds idle / peak / end |\n"
          f"|---|---|---|---|---|---|---|---|\n"
          f"| {result['honest'].get('ok', 0)} | {result['honest'].get('errors', 0)} | "
          f"{result['honest'].get('5xx', 0)} | {result['p50_ms']} ms | {result['p99_ms']} ms | "
          f"{result['max_ms']} ms | {result['idle_rss_mb']} / {max(rss)} / {rss[-1]} MB | "
          f"{result['idle_fds']} / {max(fds)} / {fds[-1]} |")
    print("hostile attempts:", json.dumps(result["hostile"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
