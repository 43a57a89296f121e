"""The playback session: ABR -> fetch -> pre-decode the next GOP -> deform + splat per frame.

Three asyncio tasks share one event loop:
- the fetcher runs the fetch schedule (stgs.client.schedule) GOP after GOP: keyframe, then the feature segment of
  the Representation the ABR rule picks, while the buffer has room;
- the decoder turns downloaded GOPs into ready GOP models in a worker thread
  (JPEG XL via OpenImageIO, video via PyAV), at most `max_decoded` at a time
  (the GOP playing and the next one), so a GOP boundary does not wait on
  decoding when the network keeps up;
- the player renders each GOP's frames (worker thread) and keeps the clock.

The clock is the presentation's real-time schedule in both modes: GOP k is due
`(k - k0) * T` after the first frame plus the stalls so far. A stall is time a
due GOP was not ready. `realtime` additionally paces frames to that schedule
and drops a frame when rendering is behind; otherwise frames render as fast
as they can (never dropped).

The module is over the usual size (~400 lines) because the Session's three tasks share one state
(clock, records, the fetch schedule) and one task group; what to fetch lives in
`stgs.client.schedule`, settings in `stgs.client.config`.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from stgs.client.abr import Decision, UpcomingGOP, make_rule
from stgs.client.clock import PlaybackClock
from stgs.client.config import PlaybackError, PlayConfig
from stgs.client.download import AbandonError, Downloader, FetchError, TransientError
from stgs.client.fetchsteps import (
    Abandoned,
    Done,
    Failed,
    Fetched,
    Outcome,
    Parallel,
    Request,
    ScheduleError,
    Step,
    Wait,
)
from stgs.client.manifest import Presentation
from stgs.client.output import NullSink, open_sink
from stgs.client.playlog import GOPRecord, playback_log
from stgs.client.schedule import FetchSchedule
from stgs.client.urlpolicy import UrlPolicy
from stgs.client.view import Trajectory, build_trajectory, parse_scene_cameras
from stgs.codec.features import features_from_frames
from stgs.codec.keyframe import Keyframe, KeyframeError, decode_keyframe
from stgs.codec.video import decode_segment
from stgs.fsio import atomic_write_bytes
from stgs.limits import MAX_DOC_BYTES, MAX_MPD_BYTES
from stgs.model.view import FrameRenderer
from stgs.mpd import MPDError
from stgs.tree import CAMERAS, STATS


@dataclass
class ReadyGOP:
    index: int
    renderer: FrameRenderer | None
    """None when the player does not decode (PlayConfig.decode False)."""


def stats_gop(stats: object, k: int, rep_ids: list[str]) -> UpcomingGOP | None:
    """GOP k's keyframe and per-rung media bits and rendered PSNR, from stats.json, or None where it does not
    say (PSNR None unless every rung has a finite one)."""
    try:
        gop = stats["gops"][k]
        if gop["index"] != k:
            return None
        keyframe = float(gop["keyframe_bytes"]) * 8
        sizes = [float(gop["representations"][r]["bytes"]) * 8 for r in rep_ids]
    except (KeyError, IndexError, TypeError, ValueError):
        return None
    if not all(math.isfinite(s) and s > 0 for s in [keyframe, *sizes]):
        return None
    try:
        psnr = [float(gop["representations"][r]["render_psnr"]) for r in rep_ids]
    except (KeyError, TypeError, ValueError):
        psnr = None
    return UpcomingGOP(keyframe, sizes, psnr if psnr and all(math.isfinite(p) for p in psnr) else None)


def physical_memory() -> int | None:
    """Bytes of RAM of this machine, or None where the OS does not say."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_decode_memory(gop_bytes: int, max_decoded: int, ram: int | None = None) -> None:
    """Refuse, before fetching anything, a presentation whose decoded GOPs (`max_decoded` of them at once) need
    more memory than the machine has."""
    ram = physical_memory() if ram is None else ram
    need = gop_bytes * max_decoded
    if ram is not None and need > ram:
        raise PlaybackError(f"decoding needs {need / 2**30:.1f} GiB ({max_decoded} GOPs of "
                            f"{gop_bytes / 2**30:.1f} GiB at once); this machine has {ram / 2**30:.1f} GiB")


class Session:
    """One playback of a Presentation (see the module docstring)."""

    def __init__(self, cfg: PlayConfig, pres: Presentation, dl: Downloader, stats: object | None,
                 cameras: list | None, on_gop: Callable[[int, FrameRenderer], None] | None = None):
        self.cfg, self.pres, self.dl, self.stats, self.cameras, self.on_gop = cfg, pres, dl, stats, cameras, on_gop
        self.T = pres.segment_seconds
        self.G = pres.shape.gop_size
        if cfg.decode:
            check_decode_memory(pres.decoded_gop_bytes(), cfg.max_decoded)
        span = pres.span(cfg.start_s, cfg.duration_s, cfg.buffer_s)
        self.k0, self.frames, self.gops, self.capacity_s = span.first_gop, span.frames, span.gops, span.buffer_s
        self.first_frame = self.k0 * self.G
        self.records = {k: GOPRecord(k) for k in self.gops}
        self.speed = cfg.speed
        self.t_start = self.now()
        self.clock = PlaybackClock(self.T, self.capacity_s, self.k0)
        rep_ids = [r.rep_id for r in pres.ladder]
        self.schedule = FetchSchedule(
            pres, make_rule(cfg.abr, [r.qp for r in pres.ladder], cfg.qp, cfg.abr_settings), self.buffer_level,
            self.capacity_s, lambda k: stats_gop(stats, k, rep_ids) if stats is not None else None,
            cfg.abr_settings, dl.settings, clock=lambda: self.now(), playing=lambda: self.clock.t0 is not None)

    def now(self) -> float:
        """The playback clock: wall seconds scaled by PlayConfig.speed (media seconds)."""
        return time.perf_counter() * self.speed

    async def sleep(self, media_s: float) -> None:
        await asyncio.sleep(media_s / self.speed)

    def buffer_level(self) -> float:
        return self.clock.buffer_level(self.now())

    # --- fetching: the schedule decides, this performs its requests with aiohttp ---

    async def drive(self, steps: Step) -> Fetched:
        """Run one of the schedule's step generators to its end; ScheduleError becomes PlaybackError."""
        outcome = None
        try:
            while True:
                item = steps.send(outcome)
                if isinstance(item, Wait):
                    await self.sleep(item.seconds)
                    outcome = None
                elif isinstance(item, Parallel):
                    outcome = tuple(await asyncio.gather(*(self.perform(r) for r in item.requests)))
                else:
                    outcome = await self.perform(item)
        except StopIteration as stop:
            return stop.value
        except ScheduleError as exc:
            raise PlaybackError(str(exc)) from None

    async def perform(self, req: Request) -> Outcome:
        """One attempt at the request (times in media seconds)."""
        verdict: list[Decision] = []

        def progress(received: int, total: int | None, elapsed: float, ttfb: float) -> bool:
            decision = req.judge(received, total, elapsed * self.speed, ttfb * self.speed)
            if decision is not None:
                verdict.append(decision)
            return decision is not None

        start = time.perf_counter()
        time_left = None if req.time_left is None else req.time_left / self.speed
        try:
            data, sample = await self.dl.fetch_once(req.url, req.kind, req.max_bytes,
                                                    progress if req.judge is not None else None, time_left)
        except AbandonError as exc:
            sample = exc.sample
            return Abandoned(sample.bytes, sample.seconds * self.speed, verdict[0], sample.ttfb * self.speed)
        except TransientError as exc:
            return Failed(f"{req.url}: {exc}", retryable=True, seconds=(time.perf_counter() - start) * self.speed)
        except FetchError as exc:
            return Failed(str(exc), retryable=False, seconds=(time.perf_counter() - start) * self.speed)
        return Done(len(data), sample.seconds * self.speed, sample.ttfb * self.speed, data)

    async def fetch_loop(self, downloaded: dict[int, asyncio.Future]) -> None:
        for k in self.gops:
            while not self.clock.has_room(self.now()):
                await self.sleep(min(0.05, self.T / 20))
            rec = self.records[k]
            start = self.now()
            rec.fetch_start_s = start - self.t_start
            try:
                item = await self.drive(self.schedule.fetch_gop(k, rec))
            except (PlaybackError, MPDError) as exc:
                downloaded[k].set_exception(exc if isinstance(exc, PlaybackError) else PlaybackError(f"GOP {k}: {exc}"))
                return
            rec.download_s = self.now() - start
            rec.fetch_end_s = rec.fetch_start_s + rec.download_s
            downloaded[k].set_result(item)
            self.clock.fetched_end = k + 1

    # --- decoding ---

    def decode_keyframe(self, item: Fetched) -> Keyframe:
        start = time.perf_counter()
        kf = decode_keyframe(item.keyframe, self.pres.shape, item.index, self.pres.max_keyframe_bytes())
        self.records[item.index].keyframe_decode_s = time.perf_counter() - start
        return kf

    def decode_features(self, item: Fetched, kf: Keyframe) -> ReadyGOP:
        rec, side = self.records[item.index], self.pres.grid_side
        start = time.perf_counter()
        self.pres.check_feature_segment(item.init, item.media, item.index)
        frames = decode_segment(item.init, item.media, self.pres.shape.num_features, 4 * side, 4 * side)
        mid = time.perf_counter()
        model = kf.to_model(features_from_frames(frames, side, kf.feature_ranges))
        renderer = FrameRenderer(model, self.cfg.native, self.cfg.precision)
        rec.feature_decode_s, rec.dequantise_s = mid - start, time.perf_counter() - mid
        return ReadyGOP(item.index, renderer)

    async def decode_gop(self, item: Fetched) -> ReadyGOP:
        """Decode one GOP; a rejected keyframe is downloaded once more, features that do not decode fall back to
        the lowest rung (the schedule decides both)."""
        k, rec = item.index, self.records[item.index]
        if not self.cfg.decode:
            return ReadyGOP(k, None)
        try:
            kf = await asyncio.to_thread(self.decode_keyframe, item)
        except KeyframeError as exc:
            item.keyframe = (await self.drive(self.schedule.refetch_keyframe(k, rec, str(exc)))).keyframe
            try:
                kf = await asyncio.to_thread(self.decode_keyframe, item)
            except KeyframeError as again:
                raise PlaybackError(f"keyframe segment of GOP {k}: {again}") from None
        try:
            return await asyncio.to_thread(self.decode_features, item, kf)
        except ValueError as exc:
            lowest = await self.drive(self.schedule.fallback(k, rec, item.rung, str(exc)))
        item.rung, item.init, item.media = lowest.rung, lowest.init, lowest.media
        try:
            return await asyncio.to_thread(self.decode_features, item, kf)
        except ValueError as exc:
            raise PlaybackError(f"feature segment of GOP {k}: {exc}") from None

    async def decode_loop(self, downloaded: dict[int, asyncio.Future], ready: dict[int, asyncio.Future],
                          slots: asyncio.Semaphore) -> None:
        for k in self.gops:
            try:
                item = await downloaded[k]
                await slots.acquire()
                ready[k].set_result(await self.decode_gop(item))
            except PlaybackError as exc:
                ready[k].set_exception(exc)
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

    async def play_loop(self, ready: dict[int, asyncio.Future], slots: asyncio.Semaphore) -> None:
        sink = NullSink()
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
        except BaseException:  # an error here or in another task (cancelled): no half-written output
            sink.abort()
            raise

    async def run(self) -> dict:
        """Fetch, decode and play as three tasks of one task group: whatever ends one of them (an error the
        schedule could not recover from, or one nobody expected) cancels the others; the log is written either
        way and the playback ends with one PlaybackError."""
        loop = asyncio.get_running_loop()
        downloaded = {k: loop.create_future() for k in self.gops}
        ready = {k: loop.create_future() for k in self.gops}
        slots = asyncio.Semaphore(self.cfg.max_decoded)
        error: BaseException | None = None
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self.fetch_loop(downloaded))
                group.create_task(self.decode_loop(downloaded, ready, slots))
                group.create_task(self.play_loop(ready, slots))
        except BaseExceptionGroup as failed:
            error = playback_failure(failed)
            raise error from None
        except BaseException as exc:  # cancelled from outside, interrupted
            error = exc
            raise
        finally:
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
                            abr=self.schedule.rule.name, wasted_bytes=self.schedule.wasted_bytes,
                            retries=self.schedule.retries + self.dl.retries,
                            error=error, gops_planned=len(self.gops),
                            extra={"realtime": self.cfg.realtime, "decode": self.cfg.decode,
                                   "error_detail": getattr(error, "detail", None)})


class InternalError(PlaybackError):
    """A failure no part of the player expected (a defect, or a resource the machine ran out of); `detail` holds
    the traceback for the playback log."""

    def __init__(self, exc: BaseException):
        super().__init__(f"playback failed unexpectedly: {type(exc).__name__}: {str(exc)[:300] or '(no message)'} "
                         "(details in the playback log)")
        self.detail = "".join(traceback.format_exception(exc))


def playback_failure(failed: BaseExceptionGroup) -> BaseException:
    """The one error a failed task group ends the playback with: a PlaybackError a task raised, else an
    interruption (KeyboardInterrupt, SystemExit) as is, else any other error as an InternalError."""
    leaves = []

    def flatten(group: BaseExceptionGroup) -> None:
        for exc in group.exceptions:
            flatten(exc) if isinstance(exc, BaseExceptionGroup) else leaves.append(exc)

    flatten(failed)
    for kind in (PlaybackError, KeyboardInterrupt, SystemExit):
        for exc in leaves:
            if isinstance(exc, kind):
                return exc
    return InternalError(leaves[0])


async def _optional_json(dl: Downloader, url: str) -> object | None:
    try:
        return json.loads(await dl.fetch(url, "document", MAX_DOC_BYTES))
    except (FetchError, json.JSONDecodeError, UnicodeDecodeError):
        return None


async def play(cfg: PlayConfig, on_gop: Callable[[int, FrameRenderer], None] | None = None) -> dict:
    """Play the presentation at cfg.url; returns the playback log (also written to cfg.log)."""
    cfg.validate()
    policy = UrlPolicy(cfg.url, cfg.urls)
    async with Downloader(cfg.download, policy) as dl:
        try:
            pres = Presentation.parse(await dl.fetch(cfg.url, "document", MAX_MPD_BYTES), cfg.url)
            policy.allow_hosts_of(pres.base)
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
