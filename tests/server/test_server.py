"""`stgs serve` on loopback: headers, ranges, caching, traversal, catalogue, metrics, load."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web
from aiohttp.test_utils import TestServer

from stgs.mpd.model import parse_mpd
from stgs.mpd.profile import FEATURE_SCHEME, KEYFRAME_SCHEME
from stgs.packager import PackConfig, pack
from stgs.server.app import SceneRunner, build_app
from stgs.server.config import ServeConfig
from stgs.server.files import BeneathOpener
from stgs.server.metrics import Metrics
from stgs.server.workers import worker_pids
from stgs.synth import SynthConfig, synthesize
from stgs.tree import expand_template

# fps = G: one-second GOPs (ffmpeg's DASH demuxer reads mediaPresentationDuration in whole seconds).
SCENE = SynthConfig(grid_side=16, num_gops=2, gop_size=6, fps=6.0, width=48, height=36, num_cameras=2,
                    fit_steps=60)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    base = tmp_path_factory.mktemp("serve")
    synthesize(SCENE, base / "model", progress=False)
    root = base / "root"
    pack(base / "model", root / "scene1", PackConfig(ladder="fixed",
                                                     qps=(20, 32), av1_qps=(16, 41), jobs=2), progress=False)
    (base / "secret.mpd").write_text("secret")
    (root / "scene1" / "escape.mpd").symlink_to(base / "secret.mpd")
    (base / "outside").mkdir()
    (base / "outside" / "x.mpd").write_text("outside")
    (root / "scene1" / "outdir").symlink_to(base / "outside", target_is_directory=True)
    (root / "scene1" / "alias.mpd").symlink_to("manifest.mpd")  # stays inside ROOT: served
    (root / "scene1" / "notes.txt").write_text("not a media file")
    (root / "scene1" / "notes.mpd").symlink_to("notes.txt")  # inside ROOT, but to a file never served
    return root


def scene_files(root: Path) -> list[str]:
    mpd = parse_mpd((root / "scene1" / "manifest.mpd").read_bytes())
    kf = mpd.adaptation_set(KEYFRAME_SCHEME).segment_template
    video = mpd.adaptation_set(FEATURE_SCHEME)
    files = ["manifest.mpd", "stats.json"] + [expand_template(kf.media, "keyframes", k) for k in range(2)]
    for rep in video.representations:
        files.append(expand_template(video.segment_template.initialization, rep.id))
        files += [expand_template(video.segment_template.media, rep.id, k) for k in range(2)]
    return files


class SceneTestServer(TestServer):
    """aiohttp's TestServer running the app as `stgs serve` does: SceneRunner, the file fast path first."""

    async def _make_runner(self, **kwargs) -> SceneRunner:
        return SceneRunner(self.app, **kwargs)


@pytest.fixture
async def scene_server():
    """Like pytest-aiohttp's aiohttp_server(app, **server_kwargs), with SceneTestServer."""
    servers = []

    async def start(app, **kwargs) -> SceneTestServer:
        server = SceneTestServer(app)
        await server.start_server(**kwargs)
        servers.append(server)
        return server

    yield start
    for server in servers:
        await server.close()


@pytest.fixture(params=["fast path", "fast path without openat2", "routed"])
async def client(request, aiohttp_client, root, monkeypatch):
    """A client of the server as `stgs serve` runs it (on a kernel with openat2, and on one without), and of the
    app alone (every request through its router)."""
    if request.param == "fast path without openat2":
        monkeypatch.setattr(BeneathOpener, "for_root", classmethod(lambda cls, root: None))
    app = build_app(ServeConfig(root=root, max_transfers=8))
    return await aiohttp_client(app if request.param == "routed" else SceneTestServer(app))


async def test_content_types_and_cache_lifetimes(client, root):
    for rel in scene_files(root):
        resp = await client.get(f"/scene1/{rel}")
        assert resp.status == 200, rel
        body = await resp.read()
        assert body == (root / "scene1" / rel).read_bytes()
        want = {".mpd": "application/dash+xml", ".json": "application/json", ".mp4": "video/mp4",
                ".m4s": "video/iso.segment", ".stgk": "application/vnd.streamstgs.keyframe"}[Path(rel).suffix]
        assert resp.headers["Content-Type"] == want
        cache = resp.headers["Cache-Control"]
        if rel.endswith((".mpd", ".json")):
            assert "max-age=2" in cache
        else:
            assert "immutable" in cache and "max-age=31536000" in cache
        assert resp.headers["Access-Control-Allow-Origin"] == "*"
        assert "ETag" in resp.headers and "Last-Modified" in resp.headers


async def test_head_has_headers_and_no_body(client, root):
    rel = scene_files(root)[-1]
    resp = await client.head(f"/scene1/{rel}")
    assert resp.status == 200
    assert int(resp.headers["Content-Length"]) == (root / "scene1" / rel).stat().st_size
    assert await resp.read() == b""


async def test_byte_ranges(client, root):
    rel = scene_files(root)[-1]
    data = (root / "scene1" / rel).read_bytes()
    size = len(data)
    for header, want, span in [("bytes=0-99", data[:100], f"0-99/{size}"),
                               ("bytes=100-", data[100:], f"100-{size - 1}/{size}"),
                               ("bytes=-50", data[-50:], f"{size - 50}-{size - 1}/{size}"),
                               (f"bytes={size - 1}-{size + 500}", data[-1:], f"{size - 1}-{size - 1}/{size}")]:
        resp = await client.get(f"/scene1/{rel}", headers={"Range": header})
        assert resp.status == 206, header
        assert resp.headers["Content-Range"] == f"bytes {span}"
        assert await resp.read() == want
    resp = await client.get(f"/scene1/{rel}", headers={"Range": f"bytes={size}-"})
    assert resp.status == 416
    assert resp.headers["Content-Range"] == f"bytes */{size}"


def etag_of(st: os.stat_result) -> str:
    return f"{st.st_mtime_ns:x}-{st.st_size:x}"


async def test_conditional_requests(client, root):
    rel = scene_files(root)[-1]
    data = (root / "scene1" / rel).read_bytes()
    first = await client.get(f"/scene1/{rel}")
    etag, modified = first.headers["ETag"], first.headers["Last-Modified"]
    assert etag == f'"{etag_of((root / "scene1" / rel).stat())}"'
    past, future = "Mon, 01 Jan 2001 00:00:00 GMT", "Fri, 01 Jan 2100 00:00:00 GMT"
    cases = [({"If-None-Match": etag}, 304, b""), ({"If-None-Match": f"W/{etag}"}, 304, b""),
             ({"If-None-Match": '"other", ' + etag}, 304, b""), ({"If-None-Match": "*"}, 304, b""),
             ({"If-Modified-Since": modified}, 304, b""), ({"If-None-Match": '"other"'}, 200, data),
             ({"If-Modified-Since": past}, 200, data),
             ({"If-None-Match": '"other"', "If-Modified-Since": modified}, 200, data),  # the tag decides
             ({"If-Match": etag}, 200, data), ({"If-Match": "*"}, 200, data), ({"If-Match": '"other"'}, 412, b""),
             ({"If-Match": f"W/{etag}"}, 412, b""),  # If-Match compares strongly
             ({"If-Unmodified-Since": past}, 412, b""), ({"If-Unmodified-Since": future}, 200, data),
             ({"If-Match": '"other"', "If-None-Match": etag}, 412, b""),  # 412 is decided first
             ({"If-Match": etag, "Range": "bytes=0-3"}, 206, data[:4]),
             ({"If-None-Match": etag, "Range": "bytes=0-3"}, 304, b"")]
    for headers, status, body in cases:
        resp = await client.get(f"/scene1/{rel}", headers=headers)
        assert (resp.status, await resp.read()) == (status, body), headers
        if status == 304:
            assert resp.headers["ETag"] == etag and resp.headers["Last-Modified"] == modified


async def test_if_range_applies_a_range_only_to_the_current_file(client, root):
    rel = scene_files(root)[-1]
    data = (root / "scene1" / rel).read_bytes()
    first = await client.get(f"/scene1/{rel}")
    etag, modified = first.headers["ETag"], first.headers["Last-Modified"]
    for if_range, status, body in [(etag, 206, data[2:5]), (modified, 206, data[2:5]), ('"stale"', 200, data),
                                   (f"W/{etag}", 200, data), ("Mon, 01 Jan 2001 00:00:00 GMT", 200, data),
                                   ("not a date", 200, data)]:
        resp = await client.get(f"/scene1/{rel}", headers={"Range": "bytes=2-4", "If-Range": if_range})
        assert (resp.status, await resp.read()) == (status, body), if_range
        assert ("Content-Range" in resp.headers) == (status == 206)


async def test_range_edge_cases_follow_rfc_9110(client, root):
    rel = scene_files(root)[-1]
    data = (root / "scene1" / rel).read_bytes()
    size = len(data)
    for header in ["bytes=5-2", "bytes=x-", "bytes=-0", f"bytes={size}-", f"bytes={size}-,{size + 5}-9999999",
                   "bytes=", "bytes=1-2-3"]:
        resp = await client.get(f"/scene1/{rel}", headers={"Range": header})
        assert resp.status == 416 and resp.headers["Content-Range"] == f"bytes */{size}", header
        assert await resp.read() == b""
    # another unit is ignored; several ranges (one satisfiable) get the whole file, not a multipart answer
    for header in ["items=0-1", "bytes=0-0,1-1", f"bytes=0-1,{size}-"]:
        resp = await client.get(f"/scene1/{rel}", headers={"Range": header})
        assert (resp.status, await resp.read()) == (200, data), header
        assert "Content-Range" not in resp.headers
    resp = await client.get(f"/scene1/{rel}", headers={"Range": "BYTES = 3-5"})
    assert (resp.status, await resp.read()) == (206, data[3:6])


async def test_a_file_path_with_a_trailing_slash_is_not_found(client):
    for path in ("/scene1/manifest.mpd/", "/scene1/manifest.mpd//", "/scene1/manifest.mpd/."):
        assert (await client.get(path)).status == 404, path
    assert (await client.get("/scene1/manifest.mpd")).status == 200


@pytest.mark.parametrize("routed", [False, True])
async def test_a_fifo_inside_root_is_not_served_and_blocks_nothing(aiohttp_client, root, tmp_path, routed):
    (tmp_path / "s").mkdir()
    shutil.copy(root / "scene1" / "manifest.mpd", tmp_path / "s" / "manifest.mpd")
    os.mkfifo(tmp_path / "s" / "pipe.m4s")  # no writer ever opens it: a blocking open would hang the event loop
    app = build_app(ServeConfig(root=tmp_path))
    client = await aiohttp_client(app if routed else SceneTestServer(app))
    resp = await asyncio.wait_for(client.get("/s/pipe.m4s"), timeout=5)
    assert resp.status == 404
    assert (await asyncio.wait_for(client.get("/s/manifest.mpd"), timeout=5)).status == 200


async def test_cors_preflight(client):
    resp = await client.options("/scene1/manifest.mpd", headers={"Origin": "https://player.example",
                                                                   "Access-Control-Request-Method": "GET"})
    assert resp.status == 204
    assert "Range" in resp.headers["Access-Control-Allow-Headers"]


async def raw_get(client, target: str) -> int:
    """Send a request line exactly as written (no client-side path normalisation); return the status."""
    reader, writer = await asyncio.open_connection(client.server.host, client.server.port)
    writer.write(f"GET {target} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode())
    await writer.drain()
    line = await reader.readline()
    writer.close()
    return int(line.split()[1])


@pytest.mark.parametrize("target", [
    "/scene1/../../secret.mpd", "/scene1/%2e%2e/%2e%2e/secret.mpd", "/%2E%2E/secret.mpd",
    "/scene1/escape.mpd", "/scene1/outdir/x.mpd",  # symlinks (file, folder) pointing out of ROOT
    "/scene1/manifest.mpd/x.mpd", "/scene1",  # a file used as a folder; a folder
    "//etc/passwd", "/etc/passwd", "/scene1/notes.txt", "/scene1/.pack-state.json",
    "/scene1/manifest.mpd%00.txt", "/scene1/..%2fmanifest.mpd", "/nope.mpd", "/scene1/notes.mpd",
])
async def test_never_leaves_root(client, target):
    assert await raw_get(client, target) == 404


@pytest.mark.parametrize("io_threads", [2, None])
async def test_file_io_on_threads_serves_the_same_bytes(aiohttp_client, root, io_threads):
    """io_threads > 0 (network storage) and None (a loop shared with other code) take aiohttp's thread pool."""
    client = await aiohttp_client(build_app(ServeConfig(root=root, io_threads=io_threads)))
    rel = scene_files(root)[2]
    data = (root / "scene1" / rel).read_bytes()
    resp = await client.get(f"/scene1/{rel}", headers={"Range": "bytes=10-"})
    assert resp.status == 206 and await resp.read() == data[10:]
    resp = await client.get(f"/scene1/{rel}")
    assert resp.status == 200 and await resp.read() == data


async def test_a_symlink_inside_root_is_served(client, root):
    resp = await client.get("/scene1/alias.mpd")
    assert resp.status == 200 and await resp.read() == (root / "scene1" / "manifest.mpd").read_bytes()


async def test_catalogue_health_and_metrics(client):
    data = await (await client.get("/scenes")).json()
    [scene] = data["scenes"]
    assert scene["name"] == "scene1" and scene["gops"] == 2
    assert scene["gop_seconds"] == pytest.approx(1.0)
    assert [r["id"] for r in scene["ladder"]] == ["qp20", "qp32", "av1q16", "av1q41"]
    assert scene["codecs"] == ["hevc", "av1"] and [r["codec"] for r in scene["ladder"]] == ["hevc"] * 2 + ["av1"] * 2
    assert (await (await client.get("/")).json()) == data
    assert (await (await client.get("/healthz")).json()) == {"status": "ok"}
    await client.get("/scene1/manifest.mpd")
    text = await (await client.get("/metrics")).text()
    assert 'stgs_http_requests_total{method="GET",status="200"}' in text
    assert "stgs_http_request_seconds_bucket" in text and "stgs_http_in_flight" in text
    sent = [line for line in text.splitlines() if line.startswith("stgs_http_sent_bytes_total")]
    assert float(sent[0].split()[1]) > 0


async def test_the_catalogue_shows_each_scene_as_a_card_with_its_face(client, root):
    data = await (await client.get("/scenes")).json()
    [scene] = data["scenes"]
    assert scene["title"] == "model" and scene["description"] == ""  # the model dir's name
    assert scene["gaussians"] == SCENE.grid_side ** 2 and scene["rungs"] == 4
    assert re.fullmatch(r"/scene1/v-[0-9a-f]+/poster\.webp", scene["poster"])
    poster = await client.get(scene["poster"])
    assert poster.status == 200 and poster.headers["Content-Type"] == "image/webp"
    assert (await poster.read())[8:12] == b"WEBP"
    page = await client.get("/", headers={"Accept": "text/html"})
    html_text = await page.text()
    csp = page.headers["Content-Security-Policy"]
    assert "img-src 'self' data:" in csp and "script-src" not in csp and "<script" not in html_text
    assert f'<img src="{scene["poster"]}" alt=""' in html_text and "<h2>model</h2>" in html_text
    assert f'<a href="{scene["player"].replace("&", "&amp;")}">watch' in html_text


async def test_a_scene_face_is_text_and_a_bad_one_falls_back(aiohttp_client, root, tmp_path):
    """A title with markup is escaped; a tree without scene.json lists under its folder's name; a poster path
    that leaves the scene's folder, a wrong format or an oversized title is ignored (the scene still lists)."""
    from stgs.tree import SCENE

    faces = {"markup": {"title": "<img src=x onerror=alert(1)>", "description": "a <b>bold</b> claim"},
             "escape": {"title": "t", "poster": "../markup/v/poster.webp"},
             "dots": {"title": "t", "poster": "v/../../x.webp"},
             "format": {"format": "something-else", "title": "t"},
             "long": {"title": "x" * 201},
             "older": None}
    for name, face in faces.items():
        shutil.copytree(root / "scene1", tmp_path / name, symlinks=True, ignore=shutil.ignore_patterns("*.txt"))
        if face is None:
            (tmp_path / name / SCENE).unlink()
        else:
            (tmp_path / name / SCENE).write_text(json.dumps({"format": "streamstgs-scene", "version": 1, **face}))
    client = await aiohttp_client(build_app(ServeConfig(root=tmp_path)))
    scenes = {s["name"]: s for s in (await (await client.get("/scenes")).json())["scenes"]}
    assert scenes["markup"]["title"] == faces["markup"]["title"]
    for name in ("escape", "dots", "format", "long", "older"):
        assert scenes[name]["title"] == name and scenes[name]["poster"] is None and "error" not in scenes[name]
    page = await (await client.get("/", headers={"Accept": "text/html"})).text()
    assert "<img src=x" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page
    assert "<b>bold</b>" not in page and "a &lt;b&gt;bold&lt;/b&gt; claim" in page


@pytest.mark.parametrize("edit", [(rb'timescale="\d+"', b'timescale="0"'),
                                  (rb'mediaPresentationDuration="[^"]+"',
                                   b'mediaPresentationDuration="PT' + b"9" * 400 + b'S"'),
                                  (rb"<MPD", b"<MPD\x00")])
async def test_one_bad_manifest_is_listed_as_bad_not_a_500_for_all(aiohttp_client, root, tmp_path, edit):
    shutil.copytree(root / "scene1", tmp_path / "good", symlinks=True)
    (tmp_path / "bad").mkdir()
    text = (root / "scene1" / "manifest.mpd").read_bytes()
    (tmp_path / "bad" / "manifest.mpd").write_bytes(re.sub(edit[0], edit[1], text, count=1))
    client = await aiohttp_client(build_app(ServeConfig(root=tmp_path)))
    for path in ("/", "/scenes"):
        resp = await client.get(path)
        assert resp.status == 200
        bad, good = (await resp.json())["scenes"]
        assert bad["name"] == "bad" and "not a playable StreamSTGS manifest" in bad["error"] and "ladder" not in bad
        assert good["name"] == "good" and good["gops"] == 2 and "error" not in good


async def test_a_slow_catalogue_scan_does_not_delay_segment_transfers(client, root, monkeypatch):
    """With io_threads=0 the loop's default executor runs calls inline: the scan must not use it."""
    import stgs.server.catalogue as catalogue

    scan = catalogue.scene_summary

    def slow_summary(name, manifest):
        time.sleep(1.5)  # a catalogue of many scenes on slow storage
        return scan(name, manifest)

    monkeypatch.setattr(catalogue, "scene_summary", slow_summary)
    segment = scene_files(root)[-1]
    listing = asyncio.ensure_future(client.get("/scenes"))
    await asyncio.sleep(0.2)  # the scan is under way
    start = time.perf_counter()
    resp = await client.get(f"/scene1/{segment}")
    assert resp.status == 200 and await resp.read() == (root / "scene1" / segment).read_bytes()
    assert time.perf_counter() - start < 0.5 and not listing.done()
    assert len((await (await listing).json())["scenes"]) == 1


async def test_a_segment_counts_once_with_its_bytes(client, root):
    """Between two /metrics answers: the first /metrics (counted once it is sent) and one segment GET."""
    def counted(text: str) -> tuple[float, float, float]:
        lines = dict(line.rsplit(" ", 1) for line in text.splitlines() if not line.startswith("#"))
        return (float(lines.get('stgs_http_requests_total{method="GET",status="200"}', 0)),
                float(lines.get("stgs_http_sent_bytes_total", 0)),
                float(lines.get("stgs_http_request_seconds_count", 0)))

    rel = scene_files(root)[-1]
    first = await (await client.get("/metrics")).read()
    assert await (await client.get(f"/scene1/{rel}")).read() == (root / "scene1" / rel).read_bytes()
    second = await (await client.get("/metrics")).read()
    (get_1, sent_1, seen_1), (get_2, sent_2, seen_2) = counted(first.decode()), counted(second.decode())
    assert get_2 - get_1 == 2 and seen_2 - seen_1 == 2
    assert sent_2 - sent_1 == len(first) + (root / "scene1" / rel).stat().st_size


def test_the_beneath_opener_refuses_every_way_out_and_every_symlink(root):
    """openat2 with RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS: files below root open; `..` out of root, absolute paths
    and symlinks (even one that stays inside root) are refused by the kernel."""
    import errno

    opener = BeneathOpener.for_root(root)
    assert opener is not None, "this kernel has openat2 (Linux 5.6+)"
    try:
        fd = opener.open("scene1/manifest.mpd")
        with open(fd, "rb") as f:
            assert f.read() == (root / "scene1" / "manifest.mpd").read_bytes()
        for path, code in [("../secret.mpd", errno.EXDEV), ("scene1/../../secret.mpd", errno.EXDEV),
                           (str(root / "scene1" / "manifest.mpd"), errno.EXDEV),
                           ("scene1/alias.mpd", errno.ELOOP), ("scene1/escape.mpd", errno.ELOOP),
                           ("scene1/outdir/x.mpd", errno.ELOOP), ("scene1/nope.mpd", errno.ENOENT)]:
            with pytest.raises(OSError) as caught:
                os.close(opener.open(path))
            assert caught.value.errno == code, path
    finally:
        opener.close()


def recording_app(root: Path, seen: list[str]) -> web.Application:
    """The server's app with a first middleware that notes each request's path."""
    @web.middleware
    async def record(request, handler):
        seen.append(request.path)
        return await handler(request)

    app = build_app(ServeConfig(root=root))
    app.middlewares.insert(0, record)
    return app


async def test_the_fast_path_answers_files_as_the_route_does(scene_server, aiohttp_server, root):
    """SceneRunner answers GET/HEADs of files (whole, ranged, conditional) before the app's router and
    middleware, with the status, headers and bytes the app's route gives; anything not a servable file reaches
    the app."""
    seen_fast, seen_routed = [], []
    fast = await scene_server(recording_app(root, seen_fast))
    routed = await aiohttp_server(recording_app(root, seen_routed))
    files = scene_files(root)
    etag = f'"{etag_of((root / "scene1" / files[-1]).stat())}"'
    variants = [{}, {"Range": "bytes=0-9"}, {"Range": "bytes=-7"}, {"If-None-Match": etag}, {"If-Match": '"x"'},
                {"Range": "bytes=99999999-"}]
    async with aiohttp.ClientSession() as session:
        for rel in files:
            for method in ("GET", "HEAD"):
                for headers in variants:
                    answers = []
                    for server in (fast, routed):
                        url = f"http://{server.host}:{server.port}/scene1/{rel}"
                        async with session.request(method, url, headers=headers) as resp:
                            kept = {k: v for k, v in resp.headers.items() if k != "Date"}
                            answers.append((resp.status, kept, await resp.read()))
                    assert answers[0] == answers[1], (method, rel, headers)
        assert seen_fast == [] and len(seen_routed) == 2 * len(files) * len(variants)
        base = f"http://{fast.host}:{fast.port}"
        async with session.get(f"{base}/scene1/nope.m4s") as resp:
            assert resp.status == 404
        async with session.get(f"{base}/healthz") as resp:
            assert resp.status == 200
    assert seen_fast == ["/scene1/nope.m4s", "/healthz"]


async def test_oversized_headers_are_refused(scene_server, root):
    server = await scene_server(build_app(ServeConfig(root=root)), max_field_size=1024)
    reader, writer = await asyncio.open_connection(server.host, server.port)
    writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 5000 + b"\r\n\r\n")
    await writer.drain()
    line = await reader.readline()
    writer.close()
    assert int(line.split()[1]) in (400, 431)


async def test_ffmpeg_decodes_every_representation_over_http(scene_server, root):
    server = await scene_server(build_app(ServeConfig(root=root)))
    url = f"http://{server.host}:{server.port}/scene1/manifest.mpd"
    # qp20, qp32 (gray 12-bit HEVC); av1q16, av1q41 (4:2:0 10-bit AV1)
    for stream, pix_fmt, picture in [(0, "gray12le", 2), (1, "gray12le", 2), (2, "yuv420p10le", 3),
                                     (3, "yuv420p10le", 3)]:
        proc = await asyncio.create_subprocess_exec(
            "ffmpeg", "-v", "error", "-i", url, "-map", f"0:{stream}", "-fps_mode", "passthrough", "-f", "rawvideo",
            "-pix_fmt", pix_fmt,
            "-", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        out, _ = await proc.communicate()
        assert proc.returncode == 0
        frames = len(out) // (64 * 64 * picture)
        assert frames == 2 * (SCENE.gop_size + 2)  # every frame of both GOPs


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


async def test_200_concurrent_clients_get_every_byte(scene_server, root):
    # one address plays 200 clients: no per-client connection cap
    server = await scene_server(build_app(ServeConfig(root=root, max_transfers=64, max_connections_per_client=0)))
    files = scene_files(root)
    want = {rel: hashlib.sha256((root / "scene1" / rel).read_bytes()).hexdigest() for rel in files}
    fds_before = open_fds()

    async def one_client(session: aiohttp.ClientSession) -> list[tuple[str, int, str]]:
        got = []
        for rel in files:
            async with session.get(f"http://{server.host}:{server.port}/scene1/{rel}") as resp:
                got.append((rel, resp.status, hashlib.sha256(await resp.read()).hexdigest()))
        return got

    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(connector=connector) as session:
        results = await asyncio.wait_for(asyncio.gather(*(one_client(session) for _ in range(200))), 120)
    for got in results:
        for rel, status, digest in got:
            assert status == 200 and digest == want[rel], rel
    await asyncio.sleep(0.2)
    assert open_fds() <= fds_before + 5, "file descriptors leaked"


async def test_a_client_that_disconnects_mid_segment_does_not_disturb_others(scene_server, root, tmp_path):
    big = root / "scene1" / "big_test_segment.m4s"
    big.write_bytes(os.urandom(32 << 20))
    try:
        server = await scene_server(build_app(ServeConfig(root=root)))
        url = f"http://{server.host}:{server.port}/scene1/big_test_segment.m4s"
        reader, writer = await asyncio.open_connection(server.host, server.port)
        writer.write(b"GET /scene1/big_test_segment.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        await writer.drain()
        await reader.read(65536)  # some of the body, then hang up
        writer.transport.abort()
        async with aiohttp.ClientSession() as session, session.get(url) as resp:
            body = await resp.read()
        assert resp.status == 200 and body == big.read_bytes()
    finally:
        big.unlink()


async def test_a_slow_reader_gets_a_big_segment_whole_and_a_stalled_one_is_cut(scene_server, root):
    """The socket takes part of a big segment at once; the rest goes out as the client reads, however slowly,
    as long as it takes something within the send timeout. A client that reads nothing holds no slot while its
    socket is full (another client is served at once from the one slot) and is cut after the send timeout."""
    big = root / "scene1" / "big_slow_segment.m4s"
    big.write_bytes(os.urandom(24 << 20))  # more than any loopback socket buffer takes at once
    try:
        server = await scene_server(build_app(ServeConfig(root=root, send_timeout=1.0, max_transfers=1)))
        url = f"http://{server.host}:{server.port}/scene1/big_slow_segment.m4s"
        async with aiohttp.ClientSession() as session, session.get(url) as resp:
            chunks = []
            while chunk := await resp.content.read(1 << 20):
                chunks.append(chunk)
                await asyncio.sleep(0.05)  # slow, but well inside the timeout
        assert resp.status == 200 and b"".join(chunks) == big.read_bytes()

        reader, writer = await asyncio.open_connection(server.host, server.port)
        writer.write(b"GET /scene1/big_slow_segment.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        await writer.drain()
        await reader.readuntil(b"\r\n\r\n")  # then reads nothing: the server's send stalls
        stalled = time.perf_counter()
        await asyncio.sleep(0.2)
        start = time.perf_counter()
        async with aiohttp.ClientSession() as session, session.get(url) as resp:  # the one slot is free
            assert resp.status == 200 and len(await resp.read()) == big.stat().st_size
        assert time.perf_counter() - start < 0.8
        await asyncio.sleep(max(0.0, stalled + 1.5 - time.perf_counter()))  # past the send timeout: cut
        got = 0
        with contextlib.suppress(ConnectionError):
            while chunk := await asyncio.wait_for(reader.read(1 << 20), 5):
                got += len(chunk)
        assert got < big.stat().st_size  # what the socket held, then the end
        writer.close()
    finally:
        big.unlink()


async def test_access_log_has_one_json_line_per_request_with_body_bytes(scene_server, root, caplog):
    import json
    import logging

    from stgs.server.metrics import JsonAccessLogger

    logger = logging.getLogger("stgs.test.access")
    server = await scene_server(build_app(ServeConfig(root=root)), access_log_class=JsonAccessLogger,
                                access_log=logger)
    rel = scene_files(root)[2]
    size = (root / "scene1" / rel).stat().st_size
    base = f"http://{server.host}:{server.port}/scene1/"
    received = []
    with caplog.at_level(logging.INFO, logger="stgs.test.access"):
        async with aiohttp.ClientSession() as session:
            for method, path, headers in [("GET", rel, {}), ("GET", rel, {"Range": "bytes=10-"}),
                                          ("HEAD", rel, {}), ("GET", "nope.m4s", {})]:
                async with session.request(method, base + path, headers=headers) as resp:
                    received.append(len(await resp.read()))
    lines = [json.loads(r.getMessage()) for r in caplog.records if r.name == "stgs.test.access"]
    assert received[:3] == [size, size - 10, 0] and received[3] > 0  # the 404 carries a short text body
    assert [(x["method"], x["status"], x["bytes"], x["range"]) for x in lines] == [
        ("GET", 200, size, None), ("GET", 206, size - 10, "bytes=10-"), ("HEAD", 200, 0, None),
        ("GET", 404, received[3], None)]
    assert all(x["path"].startswith("/scene1/") and x["seconds"] >= 0 and x["remote"] == "127.0.0.1"
               for x in lines)


def test_serve_cli_rejects_a_missing_root(tmp_path):
    from tests.conftest import run_stgs

    result = run_stgs("serve", str(tmp_path / "nowhere"))
    assert result.returncode == 2 and "not a folder" in result.stderr


def start_server(root: Path, *args: str) -> tuple[subprocess.Popen, int]:
    """A real `stgs serve` process on a free loopback port."""
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "stgs.cli", "serve", str(root), "--port", "0", "--quiet", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    return proc, int(line.rsplit(":", 1)[1].split()[0].rstrip("/"))


def sockets_of(pid: int) -> int:
    fds = Path(f"/proc/{pid}/fd")
    return sum(1 for fd in fds.iterdir() if os.readlink(fd).startswith("socket:"))


def test_workers_share_the_port_and_their_metrics(root):
    """--workers 2: the kernel spreads connections over both processes, /metrics counts every request once
    (the other worker's within Metrics.FLUSH_SECONDS), SIGTERM ends the parent with status 0 and takes the
    workers with it."""
    import signal
    import socket
    import urllib.request

    proc, port = start_server(root, "--workers", "2")
    try:
        workers = worker_pids(proc.pid)
        assert len(workers) == 2
        idle = {pid: sockets_of(pid) for pid in workers}
        held = []
        for _ in range(20):  # keep-alive connections, each answered once and left open
            sock = socket.create_connection(("127.0.0.1", port), timeout=10)
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert sock.recv(4096).startswith(b"HTTP/1.1 200")
            held.append(sock)
        assert all(sockets_of(pid) > idle[pid] for pid in workers), "a worker got no connection"
        for sock in held:
            sock.close()
        files = scene_files(root)
        for rel in files * 3:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/scene1/{rel}", timeout=10) as resp:
                assert resp.status == 200 and resp.read() == (root / "scene1" / rel).read_bytes()
        time.sleep(2 * Metrics.FLUSH_SECONDS)  # the worker not answering /metrics shows its counts once flushed
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
            text = resp.read().decode()
        [ok] = [line for line in text.splitlines()
                if line.startswith('stgs_http_requests_total{method="GET",status="200"}')]
        assert float(ok.split()[1]) == 20 + 3 * len(files)  # /metrics itself is counted after it answers
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        for pid in workers:
            assert not Path(f"/proc/{pid}").exists(), "a worker outlived the server"
    finally:
        if proc.poll() is None:
            proc.kill()


def test_sigterm_shuts_down_cleanly_during_a_transfer(root):
    """A real `stgs serve` process: SIGTERM mid-download ends it with status 0, the transfer finishes or is cut."""
    import signal
    import socket
    import time

    big = root / "scene1" / "sigterm_test_segment.m4s"
    big.write_bytes(os.urandom(64 << 20))
    proc, port = start_server(root)
    try:
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(b"GET /scene1/sigterm_test_segment.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        sock.recv(65536)  # the transfer is under way; read no more for now
        proc.send_signal(signal.SIGTERM)
        start = time.monotonic()
        received = 0
        while True:
            chunk = sock.recv(1 << 20)
            if not chunk:
                break
            received += len(chunk)
        sock.close()
        assert proc.wait(timeout=30) == 0
        assert time.monotonic() - start < 25
        assert received > 0
    finally:
        if proc.poll() is None:
            proc.kill()
        big.unlink()


def test_sigterm_cuts_a_stalled_reader_at_the_shutdown_timeout(root):
    """A client that asked for a big segment and reads nothing: the server exits shutdown-timeout seconds after
    SIGTERM, not twice that (aiohttp's graceful wait, then as long again for the cancelled handler)."""
    import signal
    import socket
    import time

    big = root / "scene1" / "stalled_reader_segment.m4s"
    big.write_bytes(bytes(64 << 20))
    proc, port = start_server(root, "--shutdown-timeout", "3")
    try:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect(("127.0.0.1", port))
        sock.sendall(b"GET /scene1/stalled_reader_segment.m4s HTTP/1.1\r\nHost: x\r\n\r\n")
        time.sleep(0.5)
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        assert time.monotonic() - start < 4.5
        sock.close()
    finally:
        if proc.poll() is None:
            proc.kill()
        big.unlink()


def test_metrics_fold_request_counts_in_at_each_exposition():
    m = Metrics()
    m.handling = 2
    for method, status, seconds, sent in (("GET", 200, 0.003, 1000), ("GET", 200, 0.2, 24), ("HEAD", 404, 0.3, 0)):
        m.answered(method, status, seconds, sent)
    lines = dict(line.rsplit(" ", 1) for line in m.exposition().decode().splitlines() if not line.startswith("#"))
    assert float(lines['stgs_http_requests_total{method="GET",status="200"}']) == 2
    assert float(lines['stgs_http_requests_total{method="HEAD",status="404"}']) == 1
    assert float(lines["stgs_http_sent_bytes_total"]) == 1024
    assert float(lines["stgs_http_in_flight"]) == 2
    assert float(lines['stgs_http_request_seconds_bucket{le="0.005"}']) == 1
    assert float(lines["stgs_http_request_seconds_count"]) == 3
    m.answered("GET", 200, 0.001, 5)
    again = m.exposition().decode()
    assert 'stgs_http_requests_total{method="GET",status="200"} 3.0' in again  # added once, not re-added
