"""Showing a still scene (manifests/PROFILE.md, "A still scene"): its static layer fetched once, decoded, and rendered
from each view the playback names. No GOP, so no clock, no ABR and no feature stream: one frame per view (one view,
or every camera of a path file), written to the same outputs as a playback's frames."""

from __future__ import annotations

import asyncio
import json
import time

from stgs.camera import Camera
from stgs.client.config import PlaybackError, PlayConfig
from stgs.client.fetch.download import Downloader, FetchError
from stgs.client.manifest import StillPresentation
from stgs.client.output import NullSink, open_view_sink
from stgs.client.resources import process_peak_rss_mb
from stgs.client.threads import ThreadBudget, render_threads, usable_cores
from stgs.client.viewpoint import build_trajectory
from stgs.codec.static import StaticSegmentError, decode_static
from stgs.fsio import atomic_write_bytes
from stgs.model.renderer import StaticDrawer, render_still
from stgs.model.static import StaticLayer

STILL_FPS = 1.0
"""The frame rate of a still's MP4 (`--out x.mp4`): one view a second."""


def still_views(cfg: PlayConfig, cameras: list[Camera] | None, layer: StaticLayer) -> list[Camera]:
    """The views a still is shown from: every camera of a path file, else the one view the ViewSpec names (a scene
    camera, an explicit pose, or the orbit's first)."""
    trajectory = build_trajectory(cfg.view, cameras, layer, 1)
    return trajectory.cameras if cfg.view.camera is None and cfg.view.eye is None and cfg.view.path != "orbit" \
        else trajectory.cameras[:1]


async def show_still(cfg: PlayConfig, pres: StillPresentation, dl: Downloader, cameras: list[Camera] | None,
                     requested: float) -> dict:
    """Fetch, decode and render the still at `pres`; returns its log (also written to cfg.log). `requested`:
    time.perf_counter() of the manifest's request."""
    log: dict = {"url": cfg.url, "still": True, "frames": 0, "static_bytes": None, "download_s": None,
                 "decode_s": None, "render_ms": [], "time_to_first_frame_s": None, "error": None}
    sink = NullSink()
    try:
        start = time.perf_counter()
        try:
            data = await dl.fetch(pres.static_url(), "static", pres.max_static_bytes())
        except FetchError as exc:
            raise PlaybackError(f"static layer: {exc}") from None
        log |= {"static_bytes": len(data), "download_s": time.perf_counter() - start}
        if not cfg.decode:
            return log
        start = time.perf_counter()
        try:
            layer = await asyncio.to_thread(decode_static, data, pres.static.capacity, pres.static.sh_degree,
                                            pres.max_static_bytes())
        except StaticSegmentError as exc:
            raise PlaybackError(f"static layer: {exc}") from None
        log["decode_s"] = time.perf_counter() - start
        views = still_views(cfg, cameras, layer)
        sink = open_view_sink(cfg.out, STILL_FPS, views)
        drawer = StaticDrawer(layer)
        threads = ThreadBudget.for_cores(usable_cores(), cfg.render_threads, cfg.decode_threads).render
        with render_threads(threads):
            for j, cam in enumerate(views):
                start = time.perf_counter()
                image = await asyncio.to_thread(render_still, drawer, cam, None, cfg.native)
                log["render_ms"].append((time.perf_counter() - start) * 1e3)
                if j == 0:
                    log["time_to_first_frame_s"] = time.perf_counter() - requested
                await asyncio.to_thread(sink.write, j, image)
                log["frames"] = j + 1
        sink.close()
        return log
    except BaseException as exc:
        sink.abort()  # no half-written output
        log["error"] = str(exc) or type(exc).__name__
        raise
    finally:
        log["process_peak_rss_mb"] = process_peak_rss_mb()
        if cfg.log is not None:
            atomic_write_bytes(cfg.log, (json.dumps(log, indent=1) + "\n").encode())
