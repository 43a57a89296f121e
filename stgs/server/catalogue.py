"""The catalogue of packaged scenes at `/` and `/scenes`: JSON, or at `/` for a browser (Accept: text/html) a page
of cards (poster, title, duration or "still", Gaussians, rungs) that link each playable scene to the web player
(`/player/?mpd=...`). Title, description and poster come from the scene's scene.json (stgs pack); a tree without
one lists under its folder's name, without a poster.

The scan reads and parses every scene's MPD: it runs on a thread of its own, never on the event loop (with
io_threads=0 the loop's default executor runs calls inline), so a large catalogue does not delay transfers."""

from __future__ import annotations

import asyncio
import html
import json
import logging
import re
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlencode

from aiohttp import web

from stgs.errors import MPDError
from stgs.limits import MAX_DESCRIPTION_CHARS, MAX_DOC_BYTES, MAX_TITLE_CHARS
from stgs.mpd.model import AdaptationSet, read_mpd
from stgs.mpd.profile import (
    FEATURE_SCHEME,
    KEYFRAME_SCHEME,
    STATIC_SCHEME,
    KeyframeDescriptor,
    StaticLayerDescriptor,
    feature_set_codec,
    still_static_set,
)
from stgs.server.config import CORS_HEADERS, ROOT_KEY
from stgs.server.player import PAGE_HEADERS, PLAYER_PREFIX
from stgs.tree import MANIFEST, SCENE, SCENE_FORMAT

CATALOGUE_CSP = ("default-src 'none'; style-src 'unsafe-inline'; img-src 'self' data:; base-uri 'none'; "
                 "form-action 'none'; frame-ancestors 'none'")
"""The catalogue page runs no script at all; its only images are the scenes' posters, from this server (and an
empty data: icon, so that the browser asks for no favicon)."""


def manifest_url(name: str) -> str:
    """The URL path of scene `name`'s MPD ("." is a scene at ROOT itself)."""
    return f"/{MANIFEST}" if name == "." else f"/{name}/{MANIFEST}"


def player_url(name: str) -> str:
    """The web player's URL path for scene `name`."""
    return f"{PLAYER_PREFIX}?{urlencode({'mpd': manifest_url(name)})}"


def scene_url(name: str, rel: str) -> str:
    """The URL path of `rel` (relative to the scene's MPD) in scene `name`."""
    return f"/{rel}" if name == "." else f"/{name}/{rel}"


def scene_face(name: str, folder: Path) -> dict:
    """Title, description and poster URL of the scene in `folder` from its scene.json; the folder's name and no
    poster for a tree without one, or with one that does not hold up in every field (logged, never fatal)."""
    face = {"title": name if name != "." else folder.resolve().name, "description": "", "poster": None}
    path = folder / SCENE
    if not path.is_file():
        return face
    try:
        if path.stat().st_size > MAX_DOC_BYTES:
            raise ValueError(f"larger than {MAX_DOC_BYTES} bytes")
        doc = json.loads(path.read_bytes())
        if not isinstance(doc, dict) or doc.get("format") != SCENE_FORMAT:
            raise ValueError(f"not a {SCENE_FORMAT} document")
        title, description, poster = doc.get("title"), doc.get("description", ""), doc.get("poster")
        if not isinstance(title, str) or not title.strip() or len(title) > MAX_TITLE_CHARS:
            raise ValueError(f"title must be a string of 1..{MAX_TITLE_CHARS} characters")
        if not isinstance(description, str) or len(description) > MAX_DESCRIPTION_CHARS:
            raise ValueError(f"description must be a string of at most {MAX_DESCRIPTION_CHARS} characters")
        poster_url = None if poster is None else scene_url(name, checked_poster(folder, poster))
        face = {"title": title, "description": description, "poster": poster_url}
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        logging.getLogger("stgs.server").warning("%s: ignored (%s)", path, exc)
    return face


POSTER_PATH = re.compile(r"[\w.-]+(/[\w.-]+)*\.webp", re.ASCII)
"""A poster path: relative, inside the scene's folder, a WebP file (web/src/scene.ts holds the same rule)."""


def checked_poster(folder: Path, poster: object) -> str:
    """scene.json's poster path, if it names a WebP file inside the scene's folder."""
    if not isinstance(poster, str) or not POSTER_PATH.fullmatch(poster) or any(
            set(part) == {"."} for part in poster.split("/")):
        raise ValueError("poster must be a relative path to a .webp file inside the scene's folder")
    if not (folder / poster).is_file():
        raise ValueError(f"poster {poster} is missing")
    return poster


def scene_summary(name: str, manifest: Path) -> dict:
    mpd = read_mpd(manifest)
    if (still := still_static_set(mpd)) is not None:
        return still_summary(name, manifest, still)
    static = mpd.find_adaptation_set(STATIC_SCHEME)
    video = mpd.adaptation_set(FEATURE_SCHEME)
    videos = [(a, feature_set_codec(a)) for a in mpd.adaptation_sets(FEATURE_SCHEME)]
    keyframes = mpd.adaptation_set(KEYFRAME_SCHEME)
    seconds = video.segment_template.seconds
    dynamic = KeyframeDescriptor.parse(keyframes).capacity
    static_capacity = 0 if static is None else StaticLayerDescriptor.parse(static).capacity
    ladder = [{"id": r.id, "codec": codec, "bandwidth": r.bandwidth, "codecs": r.codecs}
              for a, codec in videos for r in a.representations]
    return {"name": name, "manifest": manifest_url(name), "player": player_url(name),
            **scene_face(name, manifest.parent), "gaussians": dynamic + static_capacity,
            "rungs": len(ladder), "format": 1 if static is None else 2,
            "duration": mpd.duration, "gops": round(mpd.duration / seconds), "gop_seconds": seconds,
            "static": None if static is None else {
                "capacity": static_capacity, "bandwidth": static.representations[0].bandwidth},
            "keyframe_bandwidth": keyframes.representations[0].bandwidth,
            "codecs": [codec for _, codec in videos], "ladder": ladder, "still": False}


def still_summary(name: str, manifest: Path, static: AdaptationSet) -> dict:
    """A still scene's entry (manifests/PROFILE.md, "A still scene"): its static layer, no GOP, rung or codec."""
    capacity = StaticLayerDescriptor.parse(static).capacity
    return {"name": name, "manifest": manifest_url(name), "player": player_url(name),
            **scene_face(name, manifest.parent), "gaussians": capacity, "rungs": 0, "format": 2, "still": True,
            "duration": 0.0, "gops": 0, "static": {"capacity": capacity,
                                                    "bandwidth": static.representations[0].bandwidth},
            "codecs": [], "ladder": []}


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


CARD_STYLE = ("body{font:15px system-ui,sans-serif;margin:2em;color:#1b1b1b;background:#fafafa}"
              "ul{list-style:none;padding:0;display:grid;grid-template-columns:repeat(auto-fill,minmax(16em,1fr));"
              "gap:1.2em}article{background:#fff;border:1px solid #ddd;border-radius:6px;overflow:hidden}"
              "article img,.noposter{display:block;width:100%;aspect-ratio:16/9;object-fit:cover;background:#222}"
              "article div{padding:.6em .8em}h2{font-size:1.1em;margin:.2em 0}p{margin:.3em 0}.meta{color:#555}"
              "a:focus-visible{outline:3px solid #1a5fb4;outline-offset:2px}"
              ".visually-hidden{position:absolute;width:1px;height:1px;overflow:hidden;clip:rect(0 0 0 0)}")


def duration_text(seconds: float) -> str:
    whole = round(seconds)
    return f"{seconds:.1f} s" if seconds < 60 else f"{whole // 60}:{whole % 60:02d}"


def scene_card(scene: dict) -> str:
    """One scene's card: every text escaped (a title with markup shows as text)."""
    title = html.escape(scene.get("title") or (scene["name"] if scene["name"] != "." else "scene"))
    if "error" in scene:
        return f"<li><article><div><h2>{title}</h2><p>{html.escape(scene['error'])}</p></div></article></li>"
    picture = (f'<img src="{html.escape(scene["poster"])}" alt="" loading="lazy">' if scene.get("poster")
               else '<div class="noposter"></div>')
    rungs = f"{scene['rungs']} rung{'s' if scene['rungs'] != 1 else ''}"
    meta = (f"still · {scene['gaussians']:,} Gaussians" if scene["still"] else
            f"{duration_text(scene['duration'])} · {scene['gaussians']:,} Gaussians · {rungs} "
            f"({html.escape(', '.join(scene['codecs']))})")
    watch = (f'<a href="{html.escape(scene["player"])}">{"view" if scene["still"] else "watch"} '
             f'<span class="visually-hidden">{title}</span></a>'
             if scene["still"] or "av1" in scene["codecs"]
             else "no AV1 set: browsers cannot play it (repack with --codecs hevc,av1)")
    description = f"<p>{html.escape(scene['description'])}</p>" if scene.get("description") else ""
    return (f"<li><article aria-label=\"{title}\">{picture}<div><h2>{title}</h2>{description}"
            f"<p class=\"meta\">{meta}</p><p>{watch} · <a href=\"{html.escape(scene['manifest'])}\">manifest</a>"
            f"</p></div></article></li>")


def catalogue_page(data: list[dict]) -> str:
    items = "\n".join(scene_card(scene) for scene in data) or "<li>no packaged scene here</li>"
    return ("<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            "<link rel=\"icon\" href=\"data:,\"><title>streamstgs scenes</title>"
            f"<style>{CARD_STYLE}</style></head>"
            f"<body><main><h1>Scenes</h1><ul aria-label=\"Scenes\">{items}</ul>"
            "<p>JSON: <a href=\"/scenes\">/scenes</a></p></main></body></html>")


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
