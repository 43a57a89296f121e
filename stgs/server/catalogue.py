"""The catalogue of packaged scenes at `/` and `/scenes`: JSON, or at `/` for a browser (Accept: text/html) a page
that links each playable scene to the web player (`/player/?mpd=...`).

The scan reads and parses every scene's MPD: it runs on a thread of its own, never on the event loop (with
io_threads=0 the loop's default executor runs calls inline), so a large catalogue does not delay transfers."""

from __future__ import annotations

import asyncio
import html
import logging
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlencode

from aiohttp import web

from stgs.errors import MPDError
from stgs.mpd.model import read_mpd
from stgs.mpd.profile import FEATURE_SCHEME, KEYFRAME_SCHEME, STATIC_SCHEME, StaticLayerDescriptor, feature_set_codec
from stgs.server.config import CORS_HEADERS, ROOT_KEY
from stgs.server.player import PAGE_HEADERS, PLAYER_PREFIX
from stgs.tree import MANIFEST

CATALOGUE_CSP = ("default-src 'none'; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'; "
                 "frame-ancestors 'none'")
"""The catalogue page runs no script at all."""


def manifest_url(name: str) -> str:
    """The URL path of scene `name`'s MPD ("." is a scene at ROOT itself)."""
    return f"/{MANIFEST}" if name == "." else f"/{name}/{MANIFEST}"


def player_url(name: str) -> str:
    """The web player's URL path for scene `name`."""
    return f"{PLAYER_PREFIX}?{urlencode({'mpd': manifest_url(name)})}"


def scene_summary(name: str, manifest: Path) -> dict:
    mpd = read_mpd(manifest)
    video = mpd.adaptation_set(FEATURE_SCHEME)
    videos = [(a, feature_set_codec(a)) for a in mpd.adaptation_sets(FEATURE_SCHEME)]
    keyframes = mpd.adaptation_set(KEYFRAME_SCHEME)
    static = mpd.find_adaptation_set(STATIC_SCHEME)
    seconds = video.segment_template.seconds
    return {"name": name, "manifest": manifest_url(name), "player": player_url(name),
            "format": 1 if static is None else 2,
            "duration": mpd.duration, "gops": round(mpd.duration / seconds), "gop_seconds": seconds,
            "static": None if static is None else {
                "capacity": StaticLayerDescriptor.parse(static).capacity,
                "bandwidth": static.representations[0].bandwidth},
            "keyframe_bandwidth": keyframes.representations[0].bandwidth,
            "codecs": [codec for _, codec in videos],
            "ladder": [{"id": r.id, "codec": codec, "bandwidth": r.bandwidth, "codecs": r.codecs}
                       for a, codec in videos for r in a.representations]}


def catalogue(root: Path) -> list[dict]:
    """Every packaged scene at root or one folder below; one whose manifest does not parse is listed with an
    `error` instead of its summary."""
    candidates = [(".", root / MANIFEST)]
    candidates += [(d.name, d / MANIFEST) for d in sorted(root.iterdir())
                   if d.is_dir() and not d.name.startswith(".")]
    scenes = []
    for name, manifest in candidates:
        if manifest.is_file():
            try:
                scenes.append(scene_summary(name, manifest))
            except (MPDError, OSError, IndexError, ArithmeticError, ValueError) as exc:
                # listed as bad (one broken scene must not take the catalogue down with it)
                logging.getLogger("stgs.server").warning("%s: not a playable StreamSTGS manifest (%s)", manifest, exc)
                scenes.append({"name": name, "manifest": manifest_url(name),
                               "error": f"not a playable StreamSTGS manifest: {str(exc)[:200]}"})
    return scenes


def wants_html(request: web.Request) -> bool:
    """A browser's navigation to `/` (its Accept names text/html before any JSON type)."""
    accept = request.headers.get("Accept", "")
    if request.path != "/" or "text/html" not in accept:
        return False
    json_at = accept.find("json")
    return json_at < 0 or accept.find("text/html") < json_at


def catalogue_page(data: list[dict]) -> str:
    rows = []
    for scene in data:
        name = html.escape(scene["name"] if scene["name"] != "." else "scene")
        if "error" in scene:
            rows.append(f"<li>{name}: {html.escape(scene['error'])}</li>")
            continue
        codecs = ", ".join(scene["codecs"])
        watch = (f'<a href="{html.escape(scene["player"])}">watch {name}</a>' if "av1" in scene["codecs"]
                 else f"{name} (no AV1 set: browsers cannot play it; repack with --codecs hevc,av1)")
        rows.append(f"<li>{watch} · {scene['gops']} GOPs, {scene['duration']:.1f} s, format {scene['format']}, "
                    f"{html.escape(codecs)} · <a href=\"{html.escape(scene['manifest'])}\">manifest</a></li>")
    items = "\n".join(rows) or "<li>no packaged scene here</li>"
    return ("<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>streamstgs scenes</title>"
            "<style>body{font:15px system-ui,sans-serif;margin:2em;max-width:60em}li{margin:.4em 0}</style></head>"
            f"<body><h1>Scenes</h1><ul>{items}</ul><p>JSON: <a href=\"/scenes\">/scenes</a></p></body></html>")


async def scenes(request: web.Request) -> web.Response:
    data = await asyncio.get_running_loop().run_in_executor(request.app[CATALOGUE_KEY], catalogue,
                                                            request.app[ROOT_KEY])
    if wants_html(request):
        return web.Response(text=catalogue_page(data), content_type="text/html", headers={
            **PAGE_HEADERS, "Content-Security-Policy": CATALOGUE_CSP, "Cache-Control": "no-cache", "Vary": "Accept"})
    return web.json_response({"scenes": data}, headers={"Cache-Control": "no-cache", "Vary": "Accept", **CORS_HEADERS})


CATALOGUE_KEY = web.AppKey("catalogue", ThreadPoolExecutor)


async def catalogue_thread(app: web.Application) -> AsyncIterator[None]:
    """Cleanup context: the catalogue's own thread (scans queue behind each other, transfers never wait)."""
    app[CATALOGUE_KEY] = ThreadPoolExecutor(1, "stgs-catalogue")
    yield
    app[CATALOGUE_KEY].shutdown(wait=False)
