"""`stgs play` against servers that misbehave: drip-feeding, stalling, lying about lengths, answering with another
GOP's segment, redirecting where they should not, and manifests whose BaseURL points off the server. A small
aiohttp server on loopback serves the real packed scene with one misbehaviour per test; every playback must end
(played or one PlaybackError) within a bounded time."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time
from collections import Counter
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import pytest
from aiohttp import web

from stgs.client import PlaybackError, PlayConfig, play
from stgs.client.config import ViewSpec
from stgs.client.fetch.download import DownloadSettings
from stgs.client.urlpolicy import RefusedAddressError, RefusedUrlError, UrlPolicy, UrlPolicySettings
from stgs.errors import StgsError
from tests.client.conftest import copy_tree

SMALL = ViewSpec(width=32, height=24)
FAST = DownloadSettings(retries=3, backoff_s=0.05, read_timeout_s=1.0, connect_timeout_s=1.0, total_timeout_s=3.0)

Rule = Callable[[web.Request, Path], Awaitable[web.StreamResponse]]


class HostileServer:
    """Serves `root`'s files, except that a path matching a rule's pattern is answered by the rule."""

    def __init__(self, root: Path):
        self.root = root
        self.rules: list[tuple[str, Rule]] = []
        self.hits: Counter[str] = Counter()

    def on(self, pattern: str, rule: Rule) -> None:
        self.rules.append((pattern, rule))

    async def handle(self, request: web.Request) -> web.StreamResponse:
        rel = request.match_info["tail"]
        self.hits[rel] += 1
        path = self.root / rel
        for pattern, rule in self.rules:
            if re.search(pattern, rel):
                return await rule(request, path)
        if not path.is_file():
            raise web.HTTPNotFound()
        return web.Response(body=path.read_bytes())


@contextlib.asynccontextmanager
async def hostile(server: HostileServer, host: str = "127.0.0.1") -> AsyncIterator[str]:
    """Run `server` on a free port of `host`; yields its base URL."""
    app = web.Application()
    app.router.add_get("/{tail:.*}", server.handle)
    runner = web.AppRunner(app, access_log=None, shutdown_timeout=0.5)
    await runner.setup()
    try:
        await web.TCPSite(runner, host, 0).start()
        port = runner.addresses[0][1]
        yield f"http://{host}:{port}/"
    finally:
        await runner.cleanup()


async def drip(request: web.Request, path: Path) -> web.StreamResponse:
    """The whole Content-Length announced, then a byte every 0.3 s (each under the read timeout)."""
    data = path.read_bytes()
    response = web.StreamResponse(headers={"Content-Length": str(len(data))})
    await response.prepare(request)
    for i in range(len(data)):
        await response.write(data[i:i + 1])
        await asyncio.sleep(0.3)
    return response


async def stall(request: web.Request, path: Path) -> web.StreamResponse:
    response = web.StreamResponse(headers={"Content-Length": str(path.stat().st_size)})
    await response.prepare(request)
    await asyncio.sleep(3600)
    return response


async def short_body(request: web.Request, path: Path) -> web.StreamResponse:
    """Announces the file's length, sends half of it, and closes."""
    data = path.read_bytes()
    response = web.StreamResponse(headers={"Content-Length": str(len(data))})
    await response.prepare(request)
    await response.write(data[:len(data) // 2])
    request.transport.close()
    return response


def redirect_to(target: Callable[[Path], str]) -> Rule:
    async def rule(request: web.Request, path: Path) -> web.StreamResponse:
        raise web.HTTPFound(target(path))
    return rule


def with_base_url(root: Path, base_url: str) -> None:
    mpd = root / "manifest.mpd"
    text = mpd.read_text()
    mpd.write_text(re.sub(r"(<MPD\b[^>]*>)", rf"\1<BaseURL>{base_url}</BaseURL>", text, count=1))


async def play_bounded(url: str, tmp_path: Path, limit_s: float = 30, **kwargs) -> tuple[dict | None, float]:
    """Play (or fail) within limit_s; returns the log and the seconds it took."""
    kwargs.setdefault("download", FAST)
    log = tmp_path / "log.json"
    start = time.monotonic()
    try:
        await asyncio.wait_for(play(PlayConfig(url, view=SMALL, log=log, **kwargs)), timeout=limit_s)
    finally:
        elapsed = time.monotonic() - start
    return json.loads(log.read_text()), elapsed


async def test_a_drip_feeding_server_is_cut_at_the_request_deadline(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))
    server.on(r"keyframes/gop_00000", drip)
    async with hostile(server) as base:
        start = time.monotonic()
        with pytest.raises(PlaybackError, match="no answer within 3 s"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
    # one deadline for the request and its retries: 3 s, not 4 attempts of 3 s each
    assert time.monotonic() - start < 6


async def test_a_stalled_transfer_fails_after_the_read_timeout_and_retries(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))
    server.on(r"features/qp32/seg_00001", stall)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match="GOP 1"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
    assert sum(n for rel, n in server.hits.items() if "seg_00001" in rel) >= 2  # retried within the deadline
    log = json.loads((tmp_path / "log.json").read_text())
    assert log["error"] and log["gops_played"] >= 1


async def test_a_body_shorter_than_its_length_is_retried_then_refused(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))
    server.on(r"keyframes/gop_00002", short_body)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match=r"truncated body|Not enough data to satisfy content length"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
    assert server.hits[next(rel for rel in server.hits if "gop_00002" in rel)] == 4  # 1 + 3 retries


async def test_a_length_over_the_manifest_cap_is_refused_without_reading_or_retrying(scene, tmp_path):
    async def huge(request: web.Request, path: Path) -> web.StreamResponse:
        response = web.StreamResponse(headers={"Content-Length": str(1 << 40)})
        await response.prepare(request)
        await asyncio.sleep(3600)
        return response

    server = HostileServer(copy_tree(scene, tmp_path))
    server.on(r"features/qp32/seg_00000", huge)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match=r"over the .*-byte limit"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
    assert server.hits[next(rel for rel in server.hits if "seg_00000" in rel)] == 1


async def test_a_feature_segment_of_another_gop_is_refused(scene, tmp_path):
    """Every Representation answers GOP 1's request with GOP 0's segment (as a confused cache would): the
    timeline check catches it, the fallback to the lowest rung gets the same, and the playback ends saying so."""
    root = copy_tree(scene, tmp_path)
    server = HostileServer(root)

    async def gop0(request: web.Request, path: Path) -> web.StreamResponse:
        return web.Response(body=path.with_name("seg_00000.m4s").read_bytes())

    server.on(r"features/qp\d+/seg_00001", gop0)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match=r"GOP 1: .*starts at 0\.000 s, expected 1\.000 s"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=16)
    log = json.loads((tmp_path / "log.json").read_text())
    assert log["gops_played"] == 1


async def test_a_keyframe_of_another_gop_is_refused(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))

    async def gop0(request: web.Request, path: Path) -> web.StreamResponse:
        return web.Response(body=path.with_name("gop_00000.stgk").read_bytes())

    server.on(r"keyframes/gop_00001", gop0)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match="keyframe segment of GOP 1"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)


async def test_redirects_to_another_host_are_refused_unless_allowed(scene, tmp_path):
    root = copy_tree(scene, tmp_path)
    honest = HostileServer(root)
    async with hostile(honest, "127.0.0.2") as elsewhere:
        origin = HostileServer(root)
        origin.on(r"\.(m4s|mp4|stgk)$", redirect_to(lambda path: elsewhere + str(path.relative_to(root))))
        async with hostile(origin) as base:
            with pytest.raises(PlaybackError, match=r"refused by the URL policy: host 127\.0\.0\.2"):
                await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
            assert not honest.hits, "the refused host was contacted"
            log, _ = await play_bounded(base + "manifest.mpd", tmp_path, qp=32,
                                        urls=UrlPolicySettings(hosts=("127.0.0.2",)))
    assert log["error"] is None and log["gops_played"] == 3 and honest.hits


async def test_a_redirect_loop_ends_after_a_few_hops(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))
    server.on(r"keyframes/gop_00000", redirect_to(lambda path: "/" + str(path.name)))
    server.on(r"^gop_00000", redirect_to(lambda path: "/v-x/keyframes/gop_00000.stgk"))
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match="more than 5 redirects"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
    # the MPD, one attempt's hops, the optional documents, the pinned rung's init and media (asked for with it)
    assert sum(server.hits.values()) <= 1 + 6 + 2 + 2
    assert server.hits["gop_00000.stgk"] + server.hits["v-x/keyframes/gop_00000.stgk"] <= 6


async def test_a_redirect_to_a_link_local_address_is_refused(scene, tmp_path):
    server = HostileServer(copy_tree(scene, tmp_path))
    server.on(r"keyframes/gop_00000", redirect_to(lambda path: "http://169.254.169.254/latest/meta-data/"))
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match="link-local"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32,
                               urls=UrlPolicySettings(any_host=True))


@pytest.mark.parametrize("base_url, refusal", [
    ("file:///etc/", "only http and https"),
    ("http://169.254.169.254/", "link-local"),
    ("http://[fe80::1]/", "link-local"),
])
async def test_a_base_url_off_the_policy_is_refused_at_once(scene, tmp_path, base_url, refusal):
    root = copy_tree(scene, tmp_path)
    with_base_url(root, base_url)
    server = HostileServer(root)
    async with hostile(server) as base:
        with pytest.raises(PlaybackError, match=refusal):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)
    assert json.loads((tmp_path / "log.json").read_text())["retries"] == 0  # a refusal is not retried
    assert set(server.hits) <= {"manifest.mpd", "stats.json", "cameras.json"}


@pytest.mark.parametrize("where, value", [("K", float("nan")), ("K", float("inf")), ("viewmat", float("nan"))])
async def test_cameras_json_with_non_finite_numbers_is_a_clear_error(scene, tmp_path, where, value):
    root = copy_tree(scene, tmp_path)
    doc = json.loads((root / "cameras.json").read_text())
    doc["cameras"][0][where][0][0] = value
    (root / "cameras.json").write_text(json.dumps(doc))
    async with hostile(HostileServer(root)) as base:
        with pytest.raises(StgsError, match=r"camera 0 is malformed .*must be finite"):
            await play_bounded(base + "manifest.mpd", tmp_path, qp=32)


def test_the_policy_allows_the_manifest_host_and_its_base_urls_only():
    policy = UrlPolicy("https://cdn.example.com/scenes/a/manifest.mpd")
    policy.check("https://cdn.example.com/scenes/a/v-1/seg.m4s")
    with pytest.raises(RefusedUrlError, match="neither the manifest's"):
        policy.check("https://other.example.org/seg.m4s")
    policy.allow_hosts_of("https://media.example.net/base/", "file:///etc/")
    policy.check("http://media.example.net/x.m4s")
    for url in ("http://127.0.0.1/x", "http://[::1]/x", "http://[::ffff:127.0.0.1]/x", "http://0.0.0.0/x"):
        with pytest.raises(RefusedUrlError):
            UrlPolicy("https://cdn.example.com/m.mpd", UrlPolicySettings(any_host=True)).check(url)
    UrlPolicy("http://127.0.0.1:8080/m.mpd").check("http://127.0.0.1:9000/x")  # a manifest on loopback
    UrlPolicy("https://cdn.example.com/m.mpd", UrlPolicySettings(loopback=True, any_host=True)).check("http://[::1]/")


def test_names_resolving_to_refused_addresses_are_refused():
    def results(*hosts: str) -> list[dict]:
        return [{"hostname": "h", "host": h, "port": 80, "family": 2, "proto": 0, "flags": 0} for h in hosts]

    policy = UrlPolicy("https://cdn.example.com/m.mpd", UrlPolicySettings(any_host=True))
    with pytest.raises(RefusedAddressError, match="link-local"):
        policy.resolved("metadata.internal", results("169.254.169.254"))
    assert policy.resolved("mixed.example", results("169.254.1.1", "93.184.216.34")) == results("93.184.216.34")
    with pytest.raises(RefusedAddressError, match="loopback"):
        policy.resolved("evil.example", results("127.0.0.1"))
    own = UrlPolicy("http://myhost:8080/m.mpd")  # a manifest whose own name resolves to loopback
    own.resolved("myhost", results("127.0.1.1"))
    own.check("http://myhost:8080/x.m4s")
    assert own.resolved("myhost", results("127.0.1.1"))
