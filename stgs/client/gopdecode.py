"""Turning a downloaded GOP into a playable one: keyframe decoded whole, features streamed frame by frame.

A GOP is ready to play when its keyframe (five JPEG XL images) is decoded and the first window of its
feature video (stgs.codec.stream) is in the ring, and, in a layered (format-2) scene, the static layer
(decoded once, on its own thread as soon as it arrives, and drawn with every GOP); the rest of the
feature video decodes while the GOP plays. The feature video needs only the keyframe's feature ranges
(its header): it starts decoding (once the previous GOP's has finished) before the keyframe's images
decode and the renderer is built, so that on two cores the two overlap.

The decoder fetches nothing: a keyframe that does not decode comes back as `KeyframeRejected`, a feature
segment that does not decode (at the start, or in the middle of the GOP as the renderer finds) as
`FeaturesBroken`. The session routes both to the fetch schedule (the keyframe downloaded once more; the
lowest rung's features, resumed at the frame the renderer needs: `replace_features`). A static layer that
does not decode ends the playback with one error (the dynamic layer alone is not the scene).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass

import torch

from stgs.client.config import PlaybackError, PlayConfig
from stgs.client.fetch.steps import Fetched
from stgs.client.manifest import Presentation
from stgs.client.playlog import GOPRecord
from stgs.client.threads import ThreadBudget
from stgs.codec.keyframe import Keyframe, KeyframeError, KeyframeSegment, parse_keyframe
from stgs.codec.static import StaticSegmentError, decode_static
from stgs.codec.stream import FeatureStream
from stgs.model.renderer import FrameRenderer, StaticDrawer


@dataclass
class ReadyGOP:
    """A GOP the player can render: its model (no features) and the stream that feeds them."""

    index: int
    renderer: FrameRenderer | None
    """None when the player does not decode (PlayConfig.decode False)."""
    features: FeatureStream | None = None
    item: Fetched | None = None
    keyframe: Keyframe | None = None

    def finish(self, rec: GOPRecord, epoch: float) -> None:
        """Stop the GOP's feature stream and record its per-frame decode times (`epoch`: the perf_counter()
        playback began at)."""
        if self.features is not None:
            self.features.close()
            rec.decode_at_s += [t - epoch for t in self.features.decode_at]
            rec.decode_ms += self.features.decode_ms
            rec.dequantise_ms += self.features.dequantise_ms
            rec.feature_decode_s = sum(rec.decode_ms) / 1e3
            rec.dequantise_s = sum(rec.dequantise_ms) / 1e3
            rec.ring_peak = max(rec.ring_peak, self.features.peak_held)


@dataclass
class KeyframeRejected:
    """GOP `index`'s keyframe segment did not parse or decode (damaged in transit?)."""

    index: int
    reason: str


@dataclass
class FeaturesBroken:
    """`ready`'s feature segment does not decode from frame `first` of its GOP on (0: its first window)."""

    ready: ReadyGOP
    first: int
    reason: str


class GOPDecoder:
    """Decodes the GOPs of one playback in order (one feature decoder thread at a time)."""

    def __init__(self, cfg: PlayConfig, pres: Presentation, records: dict[int, GOPRecord], budget: ThreadBudget,
                 epoch: float):
        """epoch: the time.perf_counter() the log's timelines start at (when the playback began)."""
        self.cfg, self.pres, self.records, self.budget = cfg, pres, records, budget
        self.epoch = epoch
        self.window = pres.shape.window
        self.last: FeatureStream | None = None
        self.streams: list[FeatureStream] = []
        self._static: asyncio.Task | None = None

    def start_static(self, data: bytes, rec: GOPRecord) -> None:
        """Begin decoding the static-layer segment (format 2) while the first GOP downloads."""
        if not self.cfg.decode:
            return
        static = self.pres.static
        assert static is not None  # a layered presentation's

        def decode() -> StaticDrawer:
            start = time.perf_counter()
            layer = decode_static(data, static.capacity, static.sh_degree, self.pres.max_static_bytes())
            rec.static_decode_s = time.perf_counter() - start
            return StaticDrawer(layer)  # one for every GOP's renderer: a still camera keeps the layer

        self._static = asyncio.create_task(asyncio.to_thread(decode))

    async def static_layer(self) -> StaticDrawer | None:
        """The decoded static layer's drawer (None in format 1); PlaybackError if its segment does not
        decode."""
        if self._static is None:
            return None
        try:
            return await self._static
        except StaticSegmentError as exc:
            raise PlaybackError(f"static layer: {exc}") from None

    def close(self) -> None:
        """Stop every feature stream (the end of a playback, or its failure)."""
        for stream in self.streams:
            stream.close()

    def parse_keyframe(self, item: Fetched) -> KeyframeSegment:
        rep = item.keyframe_rep
        assert item.keyframe is not None  # the player's downloads carry their bodies
        return parse_keyframe(item.keyframe, self.pres.shape, item.index, self.pres.max_keyframe_bytes(rep),
                              self.pres.keyframe_quants[rep])

    def decode_keyframe(self, segment: KeyframeSegment) -> Keyframe:
        start = time.perf_counter()
        kf = segment.decode()
        self.records[segment.gop].keyframe_decode_s = time.perf_counter() - start
        return kf

    def open_stream(self, item: Fetched, ranges: torch.Tensor, first: int,
                    after: FeatureStream | None) -> FeatureStream:
        assert item.init is not None and item.media is not None  # the player's downloads carry their bodies
        self.pres.check_feature_segment(item.init, item.media, item.index)
        stream = FeatureStream(item.init + item.media, self.pres.shape.num_features, self.pres.grid_side,
                               ranges, self.cfg.ring_frames, self.budget.decode, first,
                               name=f"GOP {item.index} features", codec=self.pres.feature_codec)
        self.streams = [s for s in self.streams if not s.finished]  # close() needs only the running ones
        self.streams.append(stream)
        return stream.start(after)

    def start_stream(self, item: Fetched, ranges: torch.Tensor, after: FeatureStream | None
                     ) -> FeatureStream | ValueError:
        """GOP `item.index`'s feature stream from frame 0, decoding once `after` has finished; the error
        instead when its segment does not match the manifest."""
        try:
            stream = self.open_stream(item, ranges, 0, after)
        except ValueError as exc:
            return exc
        self.last = stream
        return stream

    async def first_window(self, stream: FeatureStream, first: int) -> None:
        await asyncio.to_thread(stream.window, first, self.window)

    async def keyframe_and_stream(self, item: Fetched) -> tuple[Keyframe, FeatureStream | ValueError]:
        """The feature stream starts as soon as the keyframe's feature ranges are read, so that its first
        frames decode while the keyframe's images do (on the other core); KeyframeError stops it again."""
        after = self.last
        segment = await asyncio.to_thread(self.parse_keyframe, item)
        stream = self.start_stream(item, segment.feature_ranges, after)
        try:
            return await asyncio.to_thread(self.decode_keyframe, segment), stream
        except KeyframeError:
            if isinstance(stream, FeatureStream):
                stream.close()
                self.last = after
            raise

    async def decode(self, item: Fetched) -> ReadyGOP | KeyframeRejected | FeaturesBroken:
        """GOP `item.index` ready to play (its keyframe decoded, its first feature window in the ring), or what
        stopped it: its keyframe rejected, or its features broken (the GOP otherwise ready, without features)."""
        k = item.index
        if not self.cfg.decode:
            return ReadyGOP(k, None)
        try:
            kf, stream = await self.keyframe_and_stream(item)
        except KeyframeError as exc:
            return KeyframeRejected(k, str(exc))
        static = await self.static_layer()
        renderer = await asyncio.to_thread(FrameRenderer, kf.to_model(None), self.cfg.native, self.cfg.precision,
                                           static)
        if isinstance(stream, FeatureStream):
            try:
                await self.first_window(stream, 0)
            except ValueError as exc:
                stream = exc
        if isinstance(stream, ValueError):
            return FeaturesBroken(ReadyGOP(k, renderer, None, item, kf), 0, str(stream))
        return ReadyGOP(k, renderer, stream, item, kf)

    async def replace_features(self, broken: FeaturesBroken, lowest: Fetched) -> None:
        """Feed `broken.ready` from the lowest rung's feature segment (`lowest`, fetched by the schedule's
        fallback) from frame `broken.first` on; PlaybackError if that does not decode either."""
        ready = broken.ready
        k, rec = ready.index, self.records[ready.index]
        if broken.first:
            rec.events.append(f"the fallback resumes at frame {broken.first} of the GOP")
        item = ready.item
        assert item is not None and ready.keyframe is not None  # a decoded GOP
        item.rung, item.init, item.media = lowest.rung, lowest.init, lowest.media
        try:
            stream = self.open_stream(item, ready.keyframe.feature_ranges, broken.first, None)
            self.last = stream
            await self.first_window(stream, broken.first)
        except ValueError as exc:
            raise PlaybackError(f"feature segment of GOP {k}: {exc}") from None
        ready.features = stream
