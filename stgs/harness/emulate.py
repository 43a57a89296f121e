"""The emulator: the real player (`stgs play`) against the real server (`stgs serve`, a subprocess as a user
runs it) through a shaping proxy.

The proxy (aiohttp, loopback) forwards every request to the server and
delivers each segment's bytes on the schedule `stgs.harness.network.Network`
computes for the scenario's effects, in real time or scaled time (`speed`:
the player's clock and the network both run that many times faster): one
round trip (latency, jitter) before the first byte, then the body paced by
the bandwidth (outages, competing clients, loss), or a fault's HTTP status. The manifest and stats.json, fetched
before playback starts, pass unshaped; the network's clock starts at the first
segment request, as the simulator's does at its first download.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
from aiohttp import web

from stgs.client import PlayConfig, play
from stgs.client.config import ViewSpec
from stgs.errors import StgsError
from stgs.harness.network import DELIVERY_CHUNK, Network
from stgs.harness.scenario import Scenario
from stgs.loopback import on_loopback
from stgs.tree import MANIFEST, SEGMENT_SUFFIXES

SERVER_START_S = 30.0
SHAPED = SEGMENT_SUFFIXES


@contextlib.asynccontextmanager
async def shaping_proxy(upstream: str, network: Network, speed: float = 1.0) -> AsyncIterator[str]:
    """A loopback proxy to `upstream` (base URL ending in /) applying `network` with its clock running `speed`
    times faster than the wall clock; yields its base URL."""
    origin: list[float] = []
    session = aiohttp.ClientSession()

    async def forward(request: web.Request) -> web.StreamResponse:
        shaped = request.path.endswith(SHAPED)
        if shaped:
            now = time.perf_counter()
            if not origin:
                origin.append(now)
            body_start = (now - origin[0]) * speed + network.round_trip()
            status = network.fault(request.path)
            if status is not None:
                await _sleep_until(origin[0] + body_start / speed)
                return web.Response(status=status)
        async with session.get(upstream + request.path.lstrip("/")) as up:
            body = await up.read()
            status, ctype = up.status, up.headers.get("Content-Type", "application/octet-stream")
        if not shaped or status != 200:
            return web.Response(status=status, body=body, content_type=None, headers={"Content-Type": ctype})
        await _sleep_until(origin[0] + body_start / speed)
        body_start = network.queue(body_start, len(body) * 8)
        await _sleep_until(origin[0] + body_start / speed)
        resp = web.StreamResponse(status=200, headers={"Content-Type": ctype, "Content-Length": str(len(body))})
        await resp.prepare(request)
        try:
            for sent in range(0, len(body), DELIVERY_CHUNK):
                chunk = body[sent:sent + DELIVERY_CHUNK]
                await _sleep_until(origin[0] + network.finish(body_start, (sent + len(chunk)) * 8) / speed)
                await resp.write(chunk)
            await resp.write_eof()
        except (ConnectionError, aiohttp.ClientConnectionResetError):
            network.release((time.perf_counter() - origin[0]) * speed)  # the player abandoned this download
        return resp

    app = web.Application()
    app.router.add_get("/{tail:.*}", forward)
    try:
        async with on_loopback(app) as base:
            yield base
    finally:
        await session.close()


async def _sleep_until(deadline: float) -> None:
    delay = deadline - time.perf_counter()
    if delay > 0:
        await asyncio.sleep(delay)


@contextlib.asynccontextmanager
async def real_server(root: Path) -> AsyncIterator[str]:
    """`stgs serve ROOT` as a user runs it, on a free loopback port; yields its base URL."""
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "stgs.cli", "serve", str(root), "--port", "0",
                                                "--quiet", stdout=asyncio.subprocess.PIPE,
                                                stderr=asyncio.subprocess.DEVNULL)
    try:
        base = await asyncio.wait_for(_announced_url(proc), SERVER_START_S)
        yield base
    finally:
        if proc.returncode is None:
            proc.terminate()
            await proc.wait()


async def _announced_url(proc: asyncio.subprocess.Process) -> str:
    assert proc.stdout is not None  # started with stdout=PIPE
    while line := await proc.stdout.readline():
        match = re.search(rb"http://127\.0\.0\.1:\d+", line)
        if match:
            return match.group().decode() + "/"
    raise StgsError("stgs serve exited before it listened")


@contextlib.asynccontextmanager
async def scene_url(scene: str) -> AsyncIterator[str]:
    """Base URL of the scene: a real server on loopback when it is a folder."""
    if scene.startswith(("http://", "https://")):
        yield scene.rsplit("/", 1)[0] + "/"
        return
    folder = Path(scene)
    async with real_server(folder if folder.is_dir() else folder.parent) as base:
        yield base


def play_config(url: str, scenario: Scenario, rule: str, decode: bool, speed: float = 1.0) -> PlayConfig:
    return PlayConfig(url, abr=rule, qp=scenario.qp, codec=scenario.codec, buffer_s=scenario.buffer_s,
                      start_s=scenario.start_s,
                      duration_s=scenario.duration_s, realtime=True, decode=decode, speed=speed,
                      ring_frames=scenario.decode.ring_frames, render_ahead=scenario.decode.render_ahead,
                      view=ViewSpec(width=64, height=48))


async def emulate_async(scenario: Scenario, rule: str, decode: bool = False, speed: float = 1.0) -> dict:
    network = Network(scenario.effects, scenario.seed)
    async with scene_url(scenario.scene) as base, shaping_proxy(base, network, speed) as proxy:
        log = await play(play_config(proxy + MANIFEST, scenario, rule, decode, speed))
    log["engine"] = "emulate" if speed == 1 else f"emulate x{speed:g}"
    return log


def emulate(scenario: Scenario, rule: str, decode: bool = False, speed: float = 1.0) -> dict:
    """One real playback through the shaping proxy (the player's log, `engine: emulate`); `speed` > 1 runs the
    player's clock and the network that many times faster than real time (decoding off)."""
    return asyncio.run(emulate_async(scenario, rule, decode, speed))
