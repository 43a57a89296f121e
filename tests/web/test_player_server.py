"""`stgs serve` and the web player's files: /player/ with its CSP and cache lives, hashed immutable assets with
their content types, 304s, the catalogue's links, a clear 503 where the player is not built."""

from __future__ import annotations

import json
import re
import urllib.error
import urllib.request

import pytest
from aiohttp.test_utils import TestClient, TestServer

from stgs.server.app import build_app
from stgs.server.config import ServeConfig
from stgs.server.player import ASSET_CACHE, INDEX_CACHE
from tests.web.conftest import DIST, need_node


def get(url: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def test_the_player_page_and_its_assets(served):
    need_node()
    status, headers, body = get(served + "player/")
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert headers["Cache-Control"] == INDEX_CACHE
    csp = headers["Content-Security-Policy"]
    assert "script-src 'self' 'wasm-unsafe-eval'" in csp and "default-src 'none'" in csp and "unsafe-eval'" not in \
        csp.replace("'wasm-unsafe-eval'", "")
    assert headers["X-Content-Type-Options"] == "nosniff"
    names = json.loads((DIST / "assets.json").read_text())
    assert names["main"] in body.decode() and names["css"] in body.decode()
    types = {".js": "text/javascript", ".wasm": "application/wasm", ".css": "text/css"}
    for name in names.values():
        status, headers, _ = get(served + "player/" + name)
        assert status == 200, name
        assert headers["Content-Type"].startswith(types[name[name.rindex("."):]])
        assert headers["Cache-Control"] == ASSET_CACHE and headers["Content-Security-Policy"] == csp
        assert re.search(r"-[0-9A-Za-z]{8,}\.(js|wasm|css)$", name), f"{name} is not content-hashed"
        again, _, _ = get(served + "player/" + name, {"If-None-Match": headers["ETag"]})
        assert again == 304
    assert get(served + "player/assets/nope.js")[0] == 404
    assert get(served + "player/../small/manifest.mpd")[0] in (200, 404)  # normalised by the client: never the build


def test_the_catalogue_links_every_playable_scene_to_the_player(served):
    status, headers, body = get(served, {"Accept": "text/html,application/xhtml+xml,*/*;q=0.8"})
    page = body.decode()
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert "script-src" not in headers["Content-Security-Policy"] and "<script" not in page
    assert 'href="/player/?mpd=%2Fsmall%2Fmanifest.mpd"' in page
    assert "<h2>broken</h2><p>not a playable StreamSTGS manifest" in page
    status, _, body = get(served)  # no Accept: the JSON catalogue, as before
    scenes = {s["name"]: s for s in json.loads(body)["scenes"]}
    assert scenes["small"]["player"] == "/player/?mpd=%2Fsmall%2Fmanifest.mpd"


async def test_an_unbuilt_player_is_a_clear_503(tmp_path):
    app = build_app(ServeConfig(root=tmp_path, port=0, access_log=False, player_dir=tmp_path / "nothing"))
    async with TestClient(TestServer(app)) as client:
        response = await client.get("/player/")
        assert response.status == 503 and "not built" in await response.text()
        response = await client.get("/player", allow_redirects=False)
        assert response.status == 308 and response.headers["Location"] == "/player/"


@pytest.mark.parametrize("suffix, kind", [(".wasm", "application/wasm"), (".mjs", "text/javascript"),
                                          (".js", "text/javascript")])
async def test_a_tree_served_with_the_player_beside_it_gets_script_types(tmp_path, suffix, kind):
    (tmp_path / f"x{suffix}").write_bytes(b"\0asm" if suffix == ".wasm" else b"export {};")
    async with TestClient(TestServer(build_app(ServeConfig(root=tmp_path, port=0, access_log=False)))) as client:
        response = await client.get(f"/x{suffix}")
        assert response.status == 200 and response.headers["Content-Type"].startswith(kind)
