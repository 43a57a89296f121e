"""The web player at `/player/` (web/, built into web/dist by setup): its index.html with a short cache life, its
assets under content-hashed names cached as immutable, every answer with the player's Content-Security-Policy.

The build is read once at start-up into memory (a few files, the JPEG XL decoder's WASM the largest), so a
request never touches the file system and no name outside the build can be asked for.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

from aiohttp import web

from stgs.server.config import CONFIG_KEY

PLAYER_PREFIX = "/player/"
DEFAULT_PLAYER_DIR = Path(__file__).resolve().parents[2] / "web" / "dist"
"""Where setup builds the player (web/dist beside the package, in a source checkout)."""

PLAYER_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".wasm": "application/wasm",
    ".css": "text/css; charset=utf-8",
}
"""The player's files by extension (the same types FILE_TYPES gives them under ROOT)."""

PLAYER_CSP = ("default-src 'none'; script-src 'self' 'wasm-unsafe-eval'; worker-src 'self'; style-src 'self'; "
              "connect-src 'self' http: https:; img-src 'self' data: blob:; base-uri 'none'; form-action 'none'; "
              "frame-ancestors 'none'")
"""The page runs only its own scripts and WASM (compiling WASM needs 'wasm-unsafe-eval'; nothing fetched is
evaluated), may fetch scenes from any http(s) origin (CORS and the page's URL policy decide), and cannot be
framed."""

INDEX_CACHE = "public, max-age=60, must-revalidate"
ASSET_CACHE = "public, max-age=31536000, immutable"
PAGE_HEADERS = {
    "Content-Security-Policy": PLAYER_CSP,
    "Cross-Origin-Opener-Policy": "same-origin",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


@dataclass(frozen=True)
class PlayerFile:
    body: bytes
    headers: dict[str, str]


def load_player(folder: Path) -> dict[str, PlayerFile]:
    """URL path below /player/ -> file, for index.html and everything under assets/ ({} when not built)."""
    index = folder / "index.html"
    if not index.is_file():
        return {}
    files = {"": index}
    assets = folder / "assets"
    if assets.is_dir():
        files |= {f"assets/{p.name}": p for p in sorted(assets.iterdir())
                  if p.is_file() and p.suffix in PLAYER_TYPES and not p.name.startswith(".")}
    out = {}
    for name, path in files.items():
        body = path.read_bytes()
        out[name] = PlayerFile(body, {
            **PAGE_HEADERS, "Content-Type": PLAYER_TYPES[path.suffix],
            "Cache-Control": INDEX_CACHE if name == "" else ASSET_CACHE,
            "ETag": '"' + hashlib.sha256(body).hexdigest()[:32] + '"'})
    return out


PLAYER_KEY = web.AppKey("player", dict)


async def player_files(app: web.Application):
    """Cleanup context: the built player, read once."""
    folder = app[CONFIG_KEY].player_dir
    app[PLAYER_KEY] = load_player(Path(folder) if folder is not None else DEFAULT_PLAYER_DIR)
    yield


async def serve_player(request: web.Request) -> web.StreamResponse:
    files = request.app[PLAYER_KEY]
    if not files:
        return web.Response(status=503, text="the web player is not built on this server: run ./bin/stgs once "
                            "with Node.js 20 and npm installed (it builds web/dist)\n",
                            headers={"Cache-Control": "no-store"})
    name = request.match_info.get("tail", "")
    if name == "index.html":
        name = ""
    file = files.get(name)
    if file is None:
        raise web.HTTPNotFound()
    if request.headers.get("If-None-Match") == file.headers["ETag"]:
        return web.Response(status=304, headers={k: v for k, v in file.headers.items() if k != "Content-Type"})
    return web.Response(body=file.body, headers=file.headers)


async def player_root(request: web.Request) -> web.StreamResponse:
    raise web.HTTPPermanentRedirect(PLAYER_PREFIX + (f"?{request.query_string}" if request.query_string else ""))
