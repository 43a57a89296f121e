"""The playback session: ABR -> fetch -> decode the keyframe, stream the features -> deform + splat per frame.

Four asyncio tasks share one event loop:
- the fetcher runs the fetch schedule (stgs.client.fetch.schedule): a layered scene's static layer first (once, whatever
  the start GOP; it counts in start-up), then GOP after GOP: keyframe, then the feature segment of the
  Representation the ABR rule picks, while the buffer has room;
- the decoder (stgs.client.gopdecode) decodes each downloaded GOP's keyframe whole (JPEG XL via OpenImageIO)
  and starts its feature stream (stgs.codec.stream: PyAV, frame by frame into a bounded ring, in its own
  thread), at most `max_decoded` GOPs at a time (the one playing and the next); a GOP is ready when its
  first feature window is decoded, and GOP k+1's features start decoding once GOP k's are all decoded, a
  few frames before its end, so a boundary does not wait when the decoder keeps up;
- the renderer and the presenter (stgs.client.framepath) render each GOP's frames (worker thread,
  `render_threads` kernel threads) from the ring, up to `render_ahead` frame slots early, and present
  them on the clock.

The clock is the presentation's real-time schedule in both modes: GOP k is due
`(k - k0) * T` after the first frame plus the stalls so far. A stall is time a
due GOP was not ready. `realtime` additionally paces frames to that schedule
and drops a frame whose slot passes before it can be drawn (rendering behind, or its features not yet
decoded); its features are still consumed in order. Otherwise frames render as fast as they can (never
dropped). The log has per-frame decode, dequantise, wait, deform and splat times.

The Session holds what the tasks share (clock, records, the fetch schedule) and their task group; what to
fetch lives in `stgs.client.fetch.schedule`, how to decode in `stgs.client.gopdecode`, how frames are rendered and
presented in `stgs.client.framepath`, settings in `stgs.client.config`.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import TypeVar

from stgs.camera import parse_scene_cameras
from stgs.client.abr import Decision, UpcomingGOP, make_rule
from stgs.client.clock import PlaybackClock
from stgs.client.config import PlaybackError, PlayConfig
from stgs.client.failure import playback_failure
from stgs.client.fetch.download import AbandonError, Downloader, FetchError, TransientError
from stgs.client.fetch.schedule import FetchSchedule
from stgs.client.fetch.steps import (
    Abandoned,
    Done,
    Failed,
    Fetched,
    Outcome,
    Parallel,
    Request,
    ScheduleError,
    Steps,
    Wait,
)
from stgs.client.framepath import FrameHook, FramePath, Playback
from stgs.client.gopdecode import FeaturesBroken, GOPDecoder, KeyframeRejected, ReadyGOP
from stgs.client.manifest import Presentation, StillPresentation, open_presentation
from stgs.client.playlog import GOPRecord, playback_log
from stgs.client.resources import check_decode_memory, frozen_heap, process_peak_rss_mb
from stgs.client.still import show_still
from stgs.client.threads import ThreadBudget, render_threads, usable_cores
from stgs.client.urlpolicy import UrlPolicy
from stgs.errors import MPDError
from stgs.fsio import atomic_write_bytes
from stgs.limits import MAX_DOC_BYTES, MAX_MPD_BYTES
from stgs.tree import CAMERAS, STATS

T = TypeVar("T")



class Session:
    """One playback of a Presentation (see the module docstring)."""

    def __init__(self, cfg: PlayConfig, pres: Presentation, dl: Downloader, stats: object | None,
                 cameras: list | None, on_frame: FrameHook | None = None, requested: float | None = None):
        """requested: time.perf_counter() of the playback's first request (the manifest's), for the log's
        time to first frame."""
        self.cfg, self.pres, self.dl, self.stats = cfg, pres, dl, stats
        self.T = pres.segment_seconds
        if cfg.decode:
            check_decode_memory(pres.decoded_gop_bytes(cfg.ring_frames), cfg.max_decoded,
                                static_bytes=pres.static_layer_bytes())
        span = pres.span(cfg.start_s, cfg.duration_s, cfg.buffer_s)
        self.k0, self.frames, self.gops, self.capacity_s = span.first_gop, span.frames, span.gops, span.buffer_s
        self.records = {k: GOPRecord(k) for k in self.gops}
        self.speed = cfg.speed
        self.t_start = self.now()
        self.requested = self.t_start / self.speed if requested is None else requested
        self.clock = PlaybackClock(self.T, self.capacity_s, self.k0)
        rep_ids, keyframe_reps = [r.rep_id for r in pres.ladder], [r.keyframe_rep for r in pres.ladder]
        self.schedule = FetchSchedule(
            pres, make_rule(cfg.abr, [r.qp for r in pres.ladder], cfg.qp, cfg.abr_settings), self.buffer_level,
            self.capacity_s, lambda k: UpcomingGOP.from_stats(stats, k, rep_ids, keyframe_reps) if stats is not None
            else None,
            cfg.abr_settings, dl.settings, clock=lambda: self.now(), playing=lambda: self.clock.t0 is not None)
        self.budget = ThreadBudget.for_cores(usable_cores(), cfg.render_threads, cfg.decode_threads)
        self.decoder = GOPDecoder(cfg, pres, self.records, self.budget, self.t_start / self.speed)
        playback = Playback(cfg, pres, self.clock, self.records, self.gops, self.frames, self.now, self.sleep,
                            self.t_start, self.features_broken)
        self.frame_path = FramePath(playback, self.decoder, cameras, on_frame)
        if cfg.decode and cfg.ring_frames < pres.shape.window:
            raise PlaybackError(f"a ring of {cfg.ring_frames} feature frames cannot hold one frame's window of "
                                f"{pres.shape.window}")

    def now(self) -> float:
        """The playback clock: wall seconds scaled by PlayConfig.speed (media seconds)."""
        return time.perf_counter() * self.speed

    async def sleep(self, media_s: float) -> None:
        await asyncio.sleep(media_s / self.speed)

    def buffer_level(self) -> float:
        return self.clock.buffer_level(self.now())

    # --- fetching: the schedule decides, this performs its requests with aiohttp ---

    async def drive(self, steps: Steps[T]) -> T:
        """Run one of the schedule's step generators to its end; ScheduleError becomes PlaybackError."""
        outcome: Outcome | tuple[Outcome, ...] | None = None
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
        judge = req.judge

        def progress(received: int, total: int | None, elapsed: float, ttfb: float) -> bool:
            decision = judge(received, total, elapsed * self.speed, ttfb * self.speed) if judge else None
            if decision is not None:
                verdict.append(decision)
            return decision is not None

        start = time.perf_counter()
        time_left = None if req.time_left is None else req.time_left / self.speed
        try:
            data, sample = await self.dl.fetch_once(req.url, req.kind, req.max_bytes,
                                                    progress if judge is not None else None, time_left)
        except AbandonError as exc:
            sample = exc.sample
            return Abandoned(sample.bytes, sample.seconds * self.speed, verdict[0], sample.ttfb * self.speed)
        except TransientError as exc:
            return Failed(f"{req.url}: {exc}", retryable=True, seconds=(time.perf_counter() - start) * self.speed)
        except FetchError as exc:
            return Failed(str(exc), retryable=False, seconds=(time.perf_counter() - start) * self.speed)
        return Done(len(data), sample.seconds * self.speed, sample.ttfb * self.speed, data)

    async def fetch_loop(self, downloaded: dict[int, asyncio.Future]) -> None:
        if self.pres.static is not None:
            rec = self.records[self.k0]
            start = self.now()
            try:
                data = await self.drive(self.schedule.fetch_static(rec))
            except PlaybackError as exc:
                downloaded[self.k0].set_exception(exc)
                return
            assert data is not None  # this driver's downloads carry their bodies
            rec.events.append(f"static layer: {len(data)} bytes in {self.now() - start:.3f} s")
            self.decoder.start_static(data, rec)
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

    # --- decoding (stgs.client.gopdecode) ---

    async def decode_loop(self, downloaded: dict[int, asyncio.Future], ready: dict[int, asyncio.Future],
                          slots: asyncio.Semaphore) -> None:
        for k in self.gops:
            try:
                item = await downloaded[k]
                del downloaded[k]  # the playback holds only the GOPs it has not finished with, however long
                await slots.acquire()
                ready[k].set_result(await self.decode_gop(item))
            except PlaybackError as exc:
                ready[k].set_exception(exc)
                return

    async def decode_gop(self, item: Fetched) -> ReadyGOP:
        """GOP `item.index` ready to play: a keyframe the decoder rejects is downloaded once more, features that
        do not decode are replaced by the lowest rung's."""
        k = item.index
        outcome = await self.decoder.decode(item)
        if isinstance(outcome, KeyframeRejected):
            again = self.schedule.refetch_keyframe(k, self.records[k], outcome.reason, item.keyframe_rep)
            item.keyframe = (await self.drive(again)).keyframe
            outcome = await self.decoder.decode(item)
            if isinstance(outcome, KeyframeRejected):
                raise PlaybackError(f"keyframe segment of GOP {k}: {outcome.reason}")
        if isinstance(outcome, FeaturesBroken):
            await self.features_broken(outcome)
            return outcome.ready
        return outcome

    async def features_broken(self, broken: FeaturesBroken) -> None:
        """Feed a GOP whose features broke (at its start, or at the frame the renderer reached) from the lowest
        rung's segment; PlaybackError if the broken one was the lowest, or the lowest does not decode either."""
        ready = broken.ready
        k, rec = ready.index, self.records[ready.index]
        if ready.features is not None:
            ready.finish(rec, self.decoder.epoch)
        assert ready.item is not None  # a decoded GOP
        lowest = await self.drive(self.schedule.fallback(k, rec, ready.item.rung, broken.reason))
        await self.decoder.replace_features(broken, lowest)

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
            with render_threads(self.budget.render), frozen_heap():
                await self.run_tasks(downloaded, ready, slots)
        except BaseExceptionGroup as failed:
            error = playback_failure(failed)
            raise error from None
        except BaseException as exc:  # cancelled from outside, interrupted
            error = exc
            raise
        finally:
            if error is not None:
                self.frame_path.sink.abort()  # no half-written output
            self.decoder.close()
            for fut in [*downloaded.values(), *ready.values()]:
                if fut.done() and not fut.cancelled():
                    fut.exception()  # retrieved: no "exception never retrieved" warnings
            self.log = self.summary(error)
            if self.cfg.log is not None:
                atomic_write_bytes(self.cfg.log, (json.dumps(self.log, indent=1) + "\n").encode())
        return self.log

    async def run_tasks(self, downloaded: dict[int, asyncio.Future], ready: dict[int, asyncio.Future],
                        slots: asyncio.Semaphore) -> None:
        async with asyncio.TaskGroup() as group:
            group.create_task(self.fetch_loop(downloaded))
            group.create_task(self.decode_loop(downloaded, ready, slots))
            group.create_task(self.frame_path.render_loop(ready))
            group.create_task(self.frame_path.present_loop(ready, slots))

    def time_to_first_frame(self) -> float | None:
        """Seconds from the manifest's request to the first rendered frame shown (without decoding: to the
        first frame's slot); None when playback never began."""
        shown = self.frame_path.first_shown
        if shown is None:
            shown = self.clock.t0 if not self.cfg.decode else None
        return None if shown is None else (shown / self.speed - self.requested) * self.speed

    def summary(self, error: BaseException | None) -> dict:
        return playback_log([self.records[k] for k in self.gops], self.clock, url=self.cfg.url,
                            abr=self.schedule.rule.name, wasted_bytes=self.schedule.wasted_bytes,
                            retries=self.schedule.retries + self.dl.retries,
                            error=error, gops_planned=len(self.gops),
                            extra={"codec": self.pres.feature_codec.name, "realtime": self.cfg.realtime,
                                   "decode": self.cfg.decode,
                                   "threads": {"render": self.budget.render, "decode": self.budget.decode},
                                   "ring_frames": self.cfg.ring_frames,
                                   "render_ahead": self.cfg.render_ahead, "fps": self.pres.fps,
                                   "process_peak_rss_mb": process_peak_rss_mb(),
                                   "time_to_first_frame_s": self.time_to_first_frame(),
                                   "error_detail": getattr(error, "detail", None)})


async def _optional_json(dl: Downloader, url: str) -> object | None:
    try:
        return json.loads(await dl.fetch(url, "document", MAX_DOC_BYTES))
    except (FetchError, json.JSONDecodeError, UnicodeDecodeError):
        return None


async def play(cfg: PlayConfig, on_frame: FrameHook | None = None) -> dict:
    """Play the presentation at cfg.url; returns the playback log (also written to cfg.log). A still scene is shown
    instead (stgs.client.still: one frame per view, no clock; `on_frame` is not called)."""
    cfg.validate()
    requested = time.perf_counter()
    policy = UrlPolicy(cfg.url, cfg.urls)
    async with Downloader(cfg.download, policy) as dl:
        try:
            pres = open_presentation(await dl.fetch(cfg.url, "document", MAX_MPD_BYTES), cfg.url, cfg.codec)
            policy.allow_hosts_of(pres.base)
        except FetchError as exc:
            raise PlaybackError(f"cannot fetch the manifest: {exc}") from None
        except MPDError as exc:
            raise PlaybackError(f"{cfg.url}: {exc}") from None
        cameras = None
        default_orbit = cfg.view.eye is None and cfg.view.path == "orbit"  # circles inside the rig when it can
        if cfg.view.camera is not None or default_orbit:
            doc = await _optional_json(dl, pres.sibling_url(CAMERAS))
            cameras = parse_scene_cameras(doc) if doc is not None else None
        if isinstance(pres, StillPresentation):
            return await show_still(cfg, pres, dl, cameras, requested)
        stats = await _optional_json(dl, pres.sibling_url(STATS))
        return await Session(cfg, pres, dl, stats, cameras, on_frame, requested).run()
