"""The playback session: ABR -> fetch -> pre-decode the next GOP -> deform + splat per frame.

Three asyncio tasks share one event loop:
- the fetcher downloads GOP after GOP (keyframe, then the feature segment of
  the Representation the ABR rule picks) while the buffer has room;
- the decoder turns downloaded GOPs into ready GOP models in a worker thread
  (JPEG XL via OpenImageIO, video via ffmpeg), at most `max_decoded` at a time
  (the GOP playing and the next one), so a GOP boundary does not wait on
  decoding when the network keeps up;
- the player renders each GOP's frames (worker thread) and keeps the clock.

The clock is the presentation's real-time schedule in both modes: GOP k is due
`(k - k0) * T` after the first frame plus the stalls so far. A stall is time a
due GOP was not ready. `realtime` additionally paces frames to that schedule
and drops a frame when rendering is behind; otherwise frames render as fast
as they can (never dropped).
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from stgs.client.abr import (
    RULES,
    AbrSettings,
    AbrState,
    FixedRule,
    ThroughputSample,
    deciding_rule,
    make_rule,
    should_abandon,
)
from stgs.client.abr import throughput_kbps as estimate_kbps
from stgs.client.clock import PlaybackClock
from stgs.client.download import AbandonError, Downloader, DownloadSettings, FetchError
from stgs.client.manifest import MAX_INIT_BYTES, Presentation
from stgs.client.output import NullSink, open_sink
from stgs.client.playlog import GOPRecord, playback_log
from stgs.client.view import Trajectory, ViewSpec, build_trajectory, parse_scene_cameras

from stgs.codec.features import features_from_frames
from stgs.codec.keyframe import Keyframe, KeyframeError, decode_keyframe
from stgs.codec.video import decode_segment
from stgs.errors import UserError
from stgs.fsio import atomic_write_bytes
from stgs.model.native_deform import check_precision
from stgs.model.view import FrameRenderer
from stgs.mpd import MAX_MPD_BYTES, MPDError
from stgs.native.build import NativeUnavailableError
from stgs.tree import CAMERAS, STATS

MAX_DOC_BYTES = 16 << 20
"""Cap on stats.json and cameras.json."""


class PlaybackError(UserError):
    """Playback could not go on (after the retries and fallbacks the log records)."""


@dataclass
class PlayConfig:
    """Everything one playback needs (one config object flows through a run)."""

    url: str
    """URL of the MPD."""
    abr: str = "dynamic"
    """ABR rule: throughput, bola or dynamic."""
    qp: int | None = None
    """Pin the feature Representation of this QP (no adaptation)."""
    buffer_s: float | None = None
    """Most media seconds downloaded ahead (None: three GOPs)."""
    start_s: float = 0.0
    """Start at the GOP holding this presentation time."""
    duration_s: float | None = None
    """Seconds to play (None: to the end)."""
    realtime: bool = False
    """Pace frames to the clock and drop the ones rendering cannot make; else render every frame at full speed."""
    view: ViewSpec = field(default_factory=ViewSpec)
    """Viewpoint."""
    out: Path | None = None
    """PNG folder or .mp4 file (None: frames are not written)."""
    log: Path | None = None
    """Where to write the JSON playback log."""
    native: bool | None = None
    """Native deform + splat (None: when built)."""
    precision: str = "fp32"
    """Arithmetic of the native deformation: fp32, or bf16 (faster where the CPU has AMX; costs accuracy)."""
    max_decoded: int = 2
    """Decoded GOP models held at once (the one playing + pre-decoded ones)."""
    decode: bool = True
    """Decode and render (False: network and buffer only, for emulation and load tests)."""
    speed: float = 1.0
    """Media seconds per wall second of the playback clock (> 1: scaled-time emulation; decode off only)."""
    abr_settings: AbrSettings = field(default_factory=AbrSettings)
    download: DownloadSettings = field(default_factory=DownloadSettings)

    def validate(self) -> None:
        if self.abr not in RULES:
            raise UserError(f"--abr must be one of {', '.join(RULES)}, got {self.abr!r}")
        if self.buffer_s is not None and not self.buffer_s > 0:
            raise UserError("--buffer must be a positive number of seconds")
        if not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise UserError("--start must be a non-negative number of seconds")
        if self.duration_s is not None and not self.duration_s > 0:
            raise UserError("--duration must be a positive number of seconds")
        if self.max_decoded < 2:
            raise UserError("max_decoded must be >= 2 (the GOP playing and the next)")
        if not (math.isfinite(self.speed) and self.speed > 0) or (self.speed != 1 and self.decode):
            raise UserError("speed must be positive, and other than 1 only without decoding")
        if self.decode:
            try:
                check_precision(self.precision)
            except (ValueError, NativeUnavailableError) as err:
                raise UserError(f"--precision: {err}") from None
            if self.precision != "fp32" and self.native is False:
                raise UserError("--precision other than fp32 needs the native renderer")


@dataclass
class Downloaded:
    index: int
    rung: int
    keyframe: bytes
    init: bytes
    media: bytes


@dataclass
class ReadyGOP:
    index: int
    renderer: FrameRenderer | None
    """None when the player does not decode (PlayConfig.decode False)."""


def _stats_sizes(stats: object, k: int, rep_ids: list[str]) -> list[float] | None:
    """Bits of GOP k's media segment per rung, from stats.json, or None where it does not say."""
    try:
        gop = stats["gops"][k]
        if gop["index"] != k:
            return None
        sizes = [float(gop["representations"][r]["bytes"]) * 8 for r in rep_ids]
    except (KeyError, IndexError, TypeError, ValueError):
        return None
    return sizes if all(math.isfinite(s) and s > 0 for s in sizes) else None


class Session:
    """One playback of a Presentation (see the module docstring)."""

    def __init__(self, cfg: PlayConfig, pres: Presentation, dl: Downloader, stats: object | None,
                 cameras: list | None, on_gop: Callable[[int, FrameRenderer], None] | None = None):
        self.cfg, self.pres, self.dl, self.stats, self.cameras, self.on_gop = cfg, pres, dl, stats, cameras, on_gop
        self.T = pres.segment_seconds
        self.G = pres.shape.gop_size
        span = pres.span(cfg.start_s, cfg.duration_s, cfg.buffer_s)
        self.k0, self.frames, self.gops, self.capacity_s = span.first_gop, span.frames, span.gops, span.buffer_s
        self.first_frame = self.k0 * self.G
        self.rule = make_rule(cfg.abr, [r.qp for r in pres.ladder], cfg.qp, cfg.abr_settings)
        self.records = {k: GOPRecord(k) for k in self.gops}
        self.inits: dict[str, bytes] = {}
        self.samples: list[ThroughputSample] = []
        self.wasted_bytes = 0
        self.speed = cfg.speed
        self.t_start = self.now()
        self.clock = PlaybackClock(self.T, self.capacity_s, self.k0)

    def now(self) -> float:
        """The playback clock: wall seconds scaled by PlayConfig.speed (media seconds)."""
        return time.perf_counter() * self.speed

    async def sleep(self, media_s: float) -> None:
        await asyncio.sleep(media_s / self.speed)

    def buffer_level(self) -> float:
        return self.clock.buffer_level(self.now())

    # --- fetching ---

    def abr_state(self, k: int, current: int | None, keyframe_bits: float) -> AbrState:
        ladder = self.pres.ladder
        sizes = _stats_sizes(self.stats, k, [r.rep_id for r in ladder]) if self.stats is not None else None
        return AbrState([r.bandwidth for r in ladder], self.T, self.buffer_level(), self.capacity_s,
                        list(self.samples), keyframe_bits, sizes, current)

    async def fetch_loop(self, downloaded: dict[int, asyncio.Future]) -> None:
        current = None
        for k in self.gops:
            while not self.clock.has_room(self.now()):
                await self.sleep(min(0.05, self.T / 20))
            try:
                item = await self.fetch_gop(k, current)
            except (FetchError, MPDError) as exc:
                downloaded[k].set_exception(PlaybackError(f"GOP {k}: {exc}"))
                return
            current = item.rung
            downloaded[k].set_result(item)
            self.clock.fetched_end = k + 1

    async def fetch_gop(self, k: int, current: int | None) -> Downloaded:
        """GOP k's keyframe (not adaptive, so first: its download is also a throughput sample), then the
        feature segment of the rung the ABR rule picks with that keyframe's exact size in its budget."""
        rec = self.records[k]
        start = self.now()
        rec.fetch_start_s = start - self.t_start
        retries = self.dl.retries
        keyframe = await self._fetch(self.pres.keyframe_url(k), "keyframe", self.pres.max_keyframe_bytes())
        state = self.abr_state(k, current, len(keyframe) * 8)
        rung = self.rule.choose(state)
        rec.rule = deciding_rule(self.rule)
        rec.buffer_s, rec.estimate_kbps = state.buffer_s, estimate_kbps(state.samples, self.cfg.abr_settings)
        rung, init, media = await self.fetch_features(k, rung, state)
        rec.download_s = self.now() - start
        rec.fetch_end_s = rec.fetch_start_s + rec.download_s
        rec.keyframe_bytes, rec.feature_bytes = len(keyframe), len(media)
        if self.dl.retries > retries:
            rec.events.append(f"{self.dl.retries - retries} retried request(s)")
        return Downloaded(k, rung, keyframe, init, media)

    async def _fetch(self, url: str, kind: str, max_bytes: int, progress=None) -> bytes:
        data = await self.dl.fetch(url, kind, max_bytes, progress)
        sample = self.dl.samples[-1]
        if kind in ("keyframe", "media"):
            self.samples.append(ThroughputSample(sample.bytes, sample.seconds * self.speed))
        return data

    async def init_segment(self, rep: str, rec: GOPRecord) -> bytes:
        """The init segment of `rep`, downloaded once (its bytes count to the GOP that needed it first)."""
        if rep not in self.inits:
            self.inits[rep] = await self._fetch(self.pres.init_url(rep), "init", MAX_INIT_BYTES)
            rec.init_bytes += len(self.inits[rep])
        return self.inits[rep]

    async def fetch_features(self, k: int, rung: int, state: AbrState) -> tuple[int, bytes, bytes]:
        """(rung, init, media) of GOP k; abandons a too-slow download and falls back to the lowest rung on errors."""
        rec = self.records[k]
        lowest_bytes = state.sizes()[0] / 8
        adaptive = not isinstance(self.rule, FixedRule)

        def progress(received: int, total: int | None, elapsed: float) -> bool:
            return adaptive and rung > 0 and should_abandon(received, total, elapsed * self.speed,
                                                            self.buffer_level(), lowest_bytes, self.cfg.abr_settings)
        rep = self.pres.ladder[rung].rep_id
        try:
            init = await self.init_segment(rep, rec)
            url = self.pres.media_url(rep, k)
            media = await self._fetch(url, "media", self.pres.max_media_bytes(rep), progress)
            rec.ttfb_s = self.dl.samples[-1].ttfb
            return self._chosen(rec, rung, init, media)
        except AbandonError as exc:
            self.samples.append(ThroughputSample(exc.sample.bytes, exc.sample.seconds * self.speed))
            rec.abandoned_bytes += exc.sample.bytes
            self.wasted_bytes += exc.sample.bytes
            rec.events.append(f"abandoned {rep} after {exc.sample.bytes} bytes "
                              f"({exc.sample.seconds * self.speed:.2f} s)")
        except FetchError as exc:
            if rung == 0:
                raise
            rec.events.append(f"fallback from {rep}: {exc}")
        return await self.fetch_lowest(k, rec)

    async def fetch_lowest(self, k: int, rec: GOPRecord) -> tuple[int, bytes, bytes]:
        """(0, init, media) of GOP k at the lowest rung: the fallback after an abandoned or failed download."""
        low = self.pres.ladder[0].rep_id
        init = await self.init_segment(low, rec)
        media = await self._fetch(self.pres.media_url(low, k), "media", self.pres.max_media_bytes(low))
        return self._chosen(rec, 0, init, media)

    def _chosen(self, rec: GOPRecord, rung: int, init: bytes, media: bytes) -> tuple[int, bytes, bytes]:
        r = self.pres.ladder[rung]
        rec.rep, rec.qp = r.rep_id, r.qp
        return rung, init, media

    # --- decoding ---

    def decode_keyframe(self, item: Downloaded) -> Keyframe:
        start = time.perf_counter()
        kf = decode_keyframe(item.keyframe, self.pres.shape, item.index, self.pres.max_keyframe_bytes())
        self.records[item.index].keyframe_decode_s = time.perf_counter() - start
        return kf

    def decode_features(self, item: Downloaded, kf: Keyframe) -> ReadyGOP:
        rec, side = self.records[item.index], self.pres.grid_side
        start = time.perf_counter()
        frames = decode_segment(item.init, item.media, self.pres.shape.num_features, 4 * side, 4 * side)
        mid = time.perf_counter()
        model = kf.to_model(features_from_frames(frames, side, kf.feature_ranges))
        renderer = FrameRenderer(model, self.cfg.native, self.cfg.precision)
        rec.feature_decode_s, rec.dequantise_s = mid - start, time.perf_counter() - mid
        return ReadyGOP(item.index, renderer)

    async def decode_gop(self, item: Downloaded) -> ReadyGOP:
        rec = self.records[item.index]
        if not self.cfg.decode:
            return ReadyGOP(item.index, None)
        try:
            kf = await asyncio.to_thread(self.decode_keyframe, item)
        except KeyframeError as exc:  # one fresh download, in case it was damaged in transit
            rec.events.append(f"keyframe rejected, downloaded again: {exc}")
            item.keyframe = await self._fetch(self.pres.keyframe_url(item.index), "keyframe",
                                              self.pres.max_keyframe_bytes())
            try:
                kf = await asyncio.to_thread(self.decode_keyframe, item)
            except KeyframeError as again:
                raise PlaybackError(f"keyframe segment of GOP {item.index}: {again}") from None
        try:
            return await asyncio.to_thread(self.decode_features, item, kf)
        except ValueError as exc:
            if item.rung == 0:
                raise PlaybackError(f"feature segment of GOP {item.index}: {exc}") from None
            rec.events.append(f"fallback from {rec.rep}: feature segment does not decode ({exc})")
        item.rung, item.init, item.media = await self.fetch_lowest(item.index, rec)
        rec.feature_bytes += len(item.media)
        try:
            return await asyncio.to_thread(self.decode_features, item, kf)
        except ValueError as exc:
            raise PlaybackError(f"feature segment of GOP {item.index}: {exc}") from None

    async def decode_loop(self, downloaded: dict[int, asyncio.Future], ready: dict[int, asyncio.Future],
                          slots: asyncio.Semaphore) -> None:
        for k in self.gops:
            try:
                item = await downloaded[k]
                await slots.acquire()
                ready[k].set_result(await self.decode_gop(item))
            except (PlaybackError, FetchError) as exc:
                ready[k].set_exception(exc if isinstance(exc, PlaybackError) else PlaybackError(f"GOP {k}: {exc}"))
                return

    # --- playing ---

    def render(self, ready: ReadyGOP, i: int, camera) -> tuple[torch.Tensor, float, float]:
        start = time.perf_counter()
        g = ready.renderer.gaussians(i, camera)
        mid = time.perf_counter()
        image = ready.renderer.splat(g, camera, guarded=ready.renderer.guarded).clamp_(0, 1)
        return image, mid - start, time.perf_counter() - mid

    async def play_gop(self, ready: ReadyGOP, trajectory: Trajectory, sink) -> None:
        k, rec, fps = ready.index, self.records[ready.index], self.pres.fps
        gop_start = self.clock.due(k)
        for i in range(self.G):
            f = k * self.G + i
            j = f - self.first_frame
            if j >= self.frames:
                break
            rec.presented += 1
            if self.cfg.realtime:
                due = gop_start + i / fps
                now = self.now()
                if now >= due + 1 / fps:
                    rec.dropped += 1
                    sink.repeat(f)
                    continue
                if now < due:
                    await self.sleep(due - now)
            if ready.renderer is None:
                continue
            start = time.perf_counter()
            image, deform_s, splat_s = await asyncio.to_thread(self.render, ready, i, trajectory.camera(j))
            rec.render_ms.append((time.perf_counter() - start) * 1e3)
            rec.deform_ms.append(deform_s * 1e3)
            rec.splat_ms.append(splat_s * 1e3)
            await asyncio.to_thread(sink.write, f, image)
        if self.cfg.realtime:  # the last frame stays on screen for its whole interval: GOP k ends at its due + T
            end = gop_start + rec.presented / fps
            if (delay := end - self.now()) > 0:
                await self.sleep(delay)
        if self.on_gop is not None and ready.renderer is not None:
            await asyncio.to_thread(self.on_gop, k, ready.renderer)

    async def wait_ready(self, k: int, fut: asyncio.Future) -> ReadyGOP:
        rec = self.records[k]
        arrived = self.now()
        was_ready = fut.done()
        result = await fut
        ready = arrived if was_ready else self.now()
        rec.boundary_wait_s = ready - (self.t_start if k == self.k0 else arrived)
        rec.stall_s = self.clock.start(k, ready, arrived)
        rec.play_start_s = self.clock.due(k) - self.t_start
        return result

    async def run(self) -> dict:
        loop = asyncio.get_running_loop()
        downloaded = {k: loop.create_future() for k in self.gops}
        ready = {k: loop.create_future() for k in self.gops}
        slots = asyncio.Semaphore(self.cfg.max_decoded)
        tasks = [asyncio.create_task(self.fetch_loop(downloaded)),
                 asyncio.create_task(self.decode_loop(downloaded, ready, slots))]
        sink, error = NullSink(), None
        try:
            for k in self.gops:
                gop = await self.wait_ready(k, ready[k])
                if k == self.k0 and gop.renderer is not None:
                    trajectory = build_trajectory(self.cfg.view, self.cameras, gop.renderer.model,
                                                  self.turn_frames())
                    sink = open_sink(self.cfg.out, self.pres.fps, *self._frame_size(trajectory))
                elif k == self.k0:
                    trajectory = None
                await self.play_gop(gop, trajectory, sink)
                del gop
                slots.release()
            sink.close()
        except BaseException as exc:
            sink.abort()
            error = exc
            raise
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            for fut in [*downloaded.values(), *ready.values()]:
                if fut.done() and not fut.cancelled():
                    fut.exception()  # retrieved: no "exception never retrieved" warnings
            self.log = self.summary(error)
            if self.cfg.log is not None:
                atomic_write_bytes(self.cfg.log, (json.dumps(self.log, indent=1) + "\n").encode())
        return self.log

    def turn_frames(self) -> int:
        if self.cfg.view.orbit_seconds:
            return max(1, round(self.cfg.view.orbit_seconds * self.pres.fps))
        return self.frames

    def _frame_size(self, trajectory: Trajectory) -> tuple[int, int]:
        sizes = {(c.width, c.height) for c in trajectory.cameras}
        if len(sizes) > 1 and self.cfg.out is not None and Path(self.cfg.out).suffix.lower() == ".mp4":
            raise PlaybackError("an MP4 needs one image size; the camera path has several (use PNG output)")
        return next(iter(sizes))

    def summary(self, error: BaseException | None) -> dict:
        return playback_log([self.records[k] for k in self.gops], self.clock, url=self.cfg.url,
                            abr=self.rule.name, wasted_bytes=self.wasted_bytes, retries=self.dl.retries,
                            error=error, gops_planned=len(self.gops),
                            extra={"realtime": self.cfg.realtime, "decode": self.cfg.decode})


async def _optional_json(dl: Downloader, url: str) -> object | None:
    try:
        return json.loads(await dl.fetch(url, "document", MAX_DOC_BYTES))
    except (FetchError, json.JSONDecodeError, UnicodeDecodeError):
        return None


async def play(cfg: PlayConfig, on_gop: Callable[[int, FrameRenderer], None] | None = None) -> dict:
    """Play the presentation at cfg.url; returns the playback log (also written to cfg.log)."""
    cfg.validate()
    async with Downloader(cfg.download) as dl:
        try:
            pres = Presentation.parse(await dl.fetch(cfg.url, "document", MAX_MPD_BYTES), cfg.url)
        except FetchError as exc:
            raise PlaybackError(f"cannot fetch the manifest: {exc}") from None
        except MPDError as exc:
            raise PlaybackError(f"{cfg.url}: {exc}") from None
        stats = await _optional_json(dl, pres.sibling_url(STATS))
        cameras = None
        default_orbit = cfg.view.eye is None and cfg.view.path == "orbit"  # circles inside the rig when it can
        if cfg.view.camera is not None or default_orbit:
            doc = await _optional_json(dl, pres.sibling_url(CAMERAS))
            cameras = parse_scene_cameras(doc) if doc is not None else None
        return await Session(cfg, pres, dl, stats, cameras, on_gop).run()
