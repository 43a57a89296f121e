"""The frame path of a playback: render each frame up to `render_ahead` slots before it is due, present it in
its slot.

Two asyncio tasks share the Session's clock and records:
- the renderer takes GOP after GOP as the decoder makes them ready and renders their frames in order (worker
  thread, the Session's render threads), each from its feature window. In real time a frame starts
  rendering no earlier than PlayConfig.render_ahead frame intervals before its slot, and is dropped when its
  slot ends before it can start (rendering behind, or its features not decoded yet); drawn or dropped, its
  features are released in order. Without real time every frame renders as soon as the one before it.
- the presenter keeps the clock: GOP k starts at its due time; one not ready when due (a stall) starts
  `render_ahead` slots after it is ready, so that the renderer has its lead there too; the first GOP of a
  real-time playback too, or once its first frame is rendered if that is later: the first frame is drawn
  before the clock starts, because it is the slow one (cold caches, and a layered scene's static layer drawn
  whole), and started earlier it would take the lead of the frames after it (on a trained scene the first two
  frames each take longer than a slot: docs/BENCHMARKS.md, "Real-time playback"); each frame goes to the output
  at the start of its slot (or when it is rendered, if later), a dropped one repeats the last; GOP k ends when its last
  frame's interval does.

Rendering ahead lets a frame slower than a slot borrow the time the frames before it did not use: the first
frames of a GOP share the cores with the keyframe decode of the GOP after next and take longer than the others
(docs/BENCHMARKS.md, "Real-time playback"). The price is latency: a frame is rendered from the
camera of its own time, up to `render_ahead` intervals before it is shown, which matters only where the
camera follows a viewer's input.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import torch

from stgs.client.clock import PlaybackClock
from stgs.client.config import PlayConfig
from stgs.client.gopdecode import FeaturesBroken, GOPDecoder, ReadyGOP
from stgs.client.manifest import Presentation
from stgs.client.output import NullSink, open_view_sink
from stgs.client.playlog import GOPRecord
from stgs.client.viewpoint import Trajectory, build_trajectory
from stgs.codec.video import VideoError
from stgs.model.renderer import FrameRenderer

FrameHook = Callable[[int, int, FrameRenderer, list[torch.Tensor]], None]
"""Called in the render thread after each rendered frame with (GOP, frame in the GOP, the GOP's renderer,
the frame's feature window): what a caller needs to render the same frame from another camera."""


@dataclass
class FrameTiming:
    """One rendered frame and where its time went (seconds)."""

    image: torch.Tensor
    start: float
    """time.perf_counter() when the render began."""
    wait_s: float
    """Waiting for the frame's features (the decoder behind the renderer)."""
    deform_s: float
    splat_s: float


@dataclass(frozen=True)
class Playback:
    """What the frame path reads of its playback (stgs.client.session.Session holds it)."""

    cfg: PlayConfig
    pres: Presentation
    clock: PlaybackClock
    records: dict[int, GOPRecord]
    gops: list[int]
    """The GOPs played, in order."""
    frames: int
    """How many frames are played from the first GOP's first."""
    now: Callable[[], float]
    """The playback clock (media seconds)."""
    sleep: Callable[[float], Awaitable[None]]
    """Sleep that many media seconds."""
    t_start: float
    """now() when the playback began."""
    features_broken: Callable[[FeaturesBroken], Awaitable[None]]
    """Replace a GOP's feature stream that broke by the lowest rung's (the Session routes it to the schedule)."""


class FramePath:
    """Renders and presents the frames of one playback (see the module docstring)."""

    def __init__(self, playback: Playback, decoder: GOPDecoder, cameras: list | None, on_frame: FrameHook | None):
        """cameras: the scene's cameras (for a view that names one), or None; on_frame: called with every frame
        presented."""
        p = playback
        self.cfg, self.clock, self.records, self.gops = p.cfg, p.clock, p.records, p.gops
        self.decoder, self.now, self.sleep, self.cameras, self.on_frame = decoder, p.now, p.sleep, cameras, on_frame
        self.t_start, self.frames, self.features_broken = p.t_start, p.frames, p.features_broken
        self.G, self.fps = p.pres.shape.gop_size, p.pres.fps
        self.k0 = p.gops[0]
        self.sink = NullSink()
        self.trajectory: Trajectory | None = None
        self.queue: asyncio.Queue[FrameTiming | None] = asyncio.Queue(p.cfg.render_ahead + 1)
        self.lead = p.cfg.render_ahead / self.fps if p.cfg.realtime and p.cfg.decode else 0.0
        """The renderer's head start: the first GOP, and one that stalled, start this long after they are ready."""
        self.arrived = self.k0
        """The GOP the presenter has reached (playing it, or waiting for it)."""
        self.started = {k: asyncio.Event() for k in p.gops}
        """Set once GOP k's start time is known (its stall, if any, counted)."""
        self.first_shown: float | None = None
        """now() when the first rendered frame went to the output (its slot, or when it was rendered if later)."""
        self.first_drawn = asyncio.Event()
        """Set once the first GOP's first frame is rendered before the clock starts (real time only)."""
        self.first_drawn_at = 0.0

    def frame_count(self, k: int) -> int:
        """Frames of GOP k that are played (fewer than G in a last GOP cut by the duration)."""
        return max(0, min(self.G, self.frames - (k - self.k0) * self.G))

    # --- the renderer ---

    def draws_first_early(self, k: int) -> bool:
        """Whether GOP k's frame 0 is rendered before the clock starts: the first GOP's, in real time, when it
        plays at least one frame (see the module docstring)."""
        return k == self.k0 and self.cfg.realtime and self.cfg.decode and self.frame_count(k) > 0

    async def render_loop(self, ready: dict[int, asyncio.Future]) -> None:
        for k in self.gops:
            gop = await ready[k]
            first = None
            if k == self.k0:
                self.open_output(gop)
            if self.draws_first_early(k):
                first = await self.render_frame(gop, 0, self.path().camera(0), None)
                self.first_drawn_at = self.now()
                self.first_drawn.set()
            if self.arrived >= k:  # the presenter waits for GOP k: its start (after a stall) sets the slots
                await self.started[k].wait()
            await self.render_gop(gop, self.clock.due(k), first)

    async def render_gop(self, gop: ReadyGOP, gop_start: float, first: FrameTiming | None = None) -> None:
        """Render GOP `gop.index`'s frames in order into the queue (`gop_start`: when its first slot begins; GOP
        k+1 is rendered ahead only once it is ready, so no stall can move it; `first`: its frame 0, rendered
        before the clock started)."""
        k, rec, interval = gop.index, self.records[gop.index], 1 / self.fps
        for i in range(self.frame_count(k)):
            deadline = None
            if self.cfg.realtime:
                slot = gop_start + i * interval
                deadline = slot + interval
                if (early := slot - self.cfg.render_ahead * interval - self.now()) > 0:
                    await self.sleep(early)
            frame = None
            if i == 0 and first is not None:
                frame = first
            elif gop.renderer is not None and (deadline is None or self.now() < deadline):
                frame = await self.render_frame(gop, i, self.path().camera(k * self.G + i - self.k0 * self.G),
                                                deadline)
            if gop.features is not None:
                gop.features.release(i + 1)  # drawn or dropped, its features are consumed
            if frame is not None:
                rec.render_at_s.append(frame.start - self.decoder.epoch)
                rec.wait_ms.append(frame.wait_s * 1e3)
                rec.deform_ms.append(frame.deform_s * 1e3)
                rec.splat_ms.append(frame.splat_s * 1e3)
                rec.render_ms.append((frame.wait_s + frame.deform_s + frame.splat_s) * 1e3)
            await self.queue.put(frame)

    def render(self, ready: ReadyGOP, i: int, camera, deadline: float | None) -> FrameTiming | None:
        """Frame i of the GOP, once its features are decoded; None when they are not by `deadline` (seconds
        on the playback clock; None: wait as long as it takes)."""
        assert ready.features is not None and ready.renderer is not None  # a decoded GOP
        start = time.perf_counter()
        timeout = None if deadline is None else max(0.0, (deadline - self.now()) / self.cfg.speed)
        window = ready.features.window(i, self.decoder.window, timeout)
        if window is None:
            return None
        got = time.perf_counter()
        g = ready.renderer.dynamic_gaussians(i, camera, window)
        mid = time.perf_counter()
        image = ready.renderer.draw(g, camera).clamp_(0, 1)
        timing = FrameTiming(image, start, got - start, mid - got, time.perf_counter() - mid)
        if self.on_frame is not None:
            self.on_frame(ready.index, i, ready.renderer, window)
        return timing

    async def render_frame(self, ready: ReadyGOP, i: int, camera, deadline: float | None) -> FrameTiming | None:
        """render(), replacing a feature stream that breaks at frame i by the lowest rung's and trying again."""
        while True:
            try:
                return await asyncio.to_thread(self.render, ready, i, camera, deadline)
            except VideoError as exc:
                await self.features_broken(FeaturesBroken(ready, i, str(exc)))

    def path(self) -> Trajectory:
        """The camera path (open_output sets it before the first frame)."""
        assert self.trajectory is not None
        return self.trajectory

    def open_output(self, first: ReadyGOP) -> None:
        """The camera path (framed on the first GOP's model where it needs one) and the frames' output."""
        if first.renderer is None:
            return
        turn = round(self.cfg.view.orbit_seconds * self.fps) if self.cfg.view.orbit_seconds else self.frames
        self.trajectory = build_trajectory(self.cfg.view, self.cameras, first.renderer.model, max(1, turn))
        self.sink = open_view_sink(self.cfg.out, self.fps, self.trajectory.cameras)

    # --- the presenter ---

    async def present_loop(self, ready: dict[int, asyncio.Future], slots: asyncio.Semaphore) -> None:
        """Present every GOP's frames in their slots, then close the output (the Session aborts it on failure)."""
        for k in self.gops:
            gop = await self.wait_ready(k, ready[k])
            await self.present_gop(gop)
            gop.finish(self.records[k], self.decoder.epoch)
            del gop, ready[k]  # its model, keyframe and segment bytes go now, not at the playback's end
            slots.release()
        self.sink.close()

    async def present_gop(self, gop: ReadyGOP) -> None:
        k, rec = gop.index, self.records[gop.index]
        gop_start = self.clock.due(k)
        for i in range(self.frame_count(k)):
            frame = await self.queue.get()
            rec.presented += 1
            if self.cfg.realtime and (early := gop_start + i / self.fps - self.now()) > 0:
                await self.sleep(early)
            f = k * self.G + i
            if frame is not None:
                if self.first_shown is None:
                    self.first_shown = self.now()
                await asyncio.to_thread(self.sink.write, f, frame.image)
            elif gop.renderer is not None:  # rendering (or its features) could not make the frame's slot
                rec.dropped += 1
                self.sink.repeat(f)
        # in real time the last frame stays on screen for its whole interval: GOP k ends at its due + T
        if self.cfg.realtime and (delay := gop_start + rec.presented / self.fps - self.now()) > 0:
            await self.sleep(delay)

    async def wait_ready(self, k: int, fut: asyncio.Future) -> ReadyGOP:
        """GOP k once it is ready; starts it on the clock (counting the stall when it was not ready in time)."""
        rec = self.records[k]
        self.arrived = k
        arrived = self.now()
        was_ready = fut.done()
        result = await fut
        ready = arrived if was_ready else self.now()
        rec.boundary_wait_s = ready - (self.t_start if k == self.k0 else arrived)
        lead = self.lead
        if self.draws_first_early(k):
            await self.first_drawn.wait()
            lead = max(lead, self.first_drawn_at - ready)
        rec.stall_s = self.clock.start(k, ready, arrived, lead)
        rec.play_start_s = self.clock.due(k) - self.t_start
        self.started[k].set()
        return result
