"""A GOP's feature video decoded frame by frame, just ahead of the renderer, into a bounded ring.

The player does not decode a GOP's E feature frames before playing it: a `FeatureStream` decodes them in
its own thread (PyAV, `threads` libavcodec threads) and dequantises each into an (N, 16) float32 frame
(numpy on that thread, see stgs.codec.features.dequantize_frame), holding at most `capacity` frames the
renderer has not released. The renderer asks for the window of frame i (e_i … e_{i+W-1}), waiting if the
decoder is behind, and releases e_i once frame i is drawn or dropped; a frame released before it is
decoded is still decoded (HEVC frames depend on each other) but never dequantised, so a decoder that falls
behind catches up. Streams of consecutive GOPs are chained: GOP k+1's stream starts decoding when GOP k's
has decoded its last frame, so one decoder runs at a time and GOP k+1's first frames are ready while GOP
k's last ones play. Memory: `capacity` frames per stream, two streams at a GOP boundary.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import torch

from stgs.codec.features import TILES, dequantize_frame
from stgs.codec.video import HEVC, FeatureCodec, iter_frames
from stgs.model.gop import FEATURE_DIM


class StreamClosedError(RuntimeError):
    """The stream was closed while a caller waited on it."""


class FeatureStream:
    """One GOP's feature segment (init + media bytes) decoded in a thread into a ring of feature frames."""

    def __init__(self, data: bytes, frames: int, side: int, ranges: torch.Tensor, capacity: int = 8,
                 threads: int = 1, first: int = 0, name: str = "features", codec: FeatureCodec = HEVC):
        """frames: E, the count the segment must hold; side: the grid side S (frames are 4S x 4S);
        capacity: most frames held; first: frames before it are decoded but not kept (a fallback
        resuming mid-GOP); codec: the segment's codec (and so its code depth)."""
        if capacity < 1:
            raise ValueError("a feature ring holds at least one frame")
        if not 0 <= first <= frames:
            raise ValueError(f"first frame {first} is outside 0..{frames}")
        self.data, self.frames, self.side, self.capacity, self.threads = data, frames, side, capacity, threads
        self.ranges = ranges.detach().to(torch.float32).clone()
        self.name, self.codec = name, codec
        self._cond = threading.Condition()
        self._held: dict[int, torch.Tensor] = {}
        self._spare: list[torch.Tensor] = []
        self._released = first
        self._decoded = 0
        self._error: Exception | None = None
        self._closed = False
        self._turn = False
        self._finished = False
        self._next: FeatureStream | None = None
        self._thread: threading.Thread | None = None
        self.decode_ms: list[float] = []
        """Video decode milliseconds of each decoded frame."""
        self.dequantise_ms: list[float] = []
        """Dequantise milliseconds of each decoded frame (0 for a frame released before it was decoded)."""
        self.decode_at: list[float] = []
        """time.perf_counter() when each frame's decode began (for timelines)."""
        self.peak_held = 0
        """Most frames held at once."""

    # --- lifecycle ---

    def start(self, after: FeatureStream | None = None) -> FeatureStream:
        """Start the decoder thread; it decodes once `after` (the previous GOP's stream) has finished."""
        if after is None or not after._chain(self):
            self._give_turn()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()
        return self

    def _chain(self, successor: FeatureStream) -> bool:
        """Let `successor` decode after this stream finishes; False when it already has."""
        with self._cond:
            if self._finished:
                return False
            self._next = successor
            return True

    def _give_turn(self) -> None:
        with self._cond:
            self._turn = True
            self._cond.notify_all()

    def close(self) -> None:
        """Stop decoding (the thread ends at its next frame) and drop every frame held."""
        with self._cond:
            self._closed = True
            self._held.clear()
            self._spare.clear()
            self._cond.notify_all()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def finished(self) -> bool:
        """True once the decoder thread has stopped (all frames decoded, failed, or closed)."""
        with self._cond:
            return self._finished

    @property
    def error(self) -> Exception | None:
        with self._cond:
            return self._error

    # --- the renderer's side ---

    def window(self, i: int, w: int, timeout: float | None = None) -> list[torch.Tensor] | None:
        """Feature frames i … i+w-1, waiting for the decoder; None if `timeout` seconds pass first. Raises the
        decoder's VideoError when the segment ends or breaks before frame i+w-1 (any other exception of the
        decoder thread as it is: a defect), StreamClosedError when closed."""
        if not (i >= 0 and i + w <= self.frames and w >= 1):
            raise ValueError(f"frames {i}..{i + w - 1} are outside the GOP's {self.frames} feature frames")
        if w > self.capacity:
            raise ValueError(f"a window of {w} frames does not fit a ring of {self.capacity}")
        if i < self._released:
            raise ValueError(f"feature frame {i} was already released")
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._decoded < i + w and self._error is None and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left)
            if self._closed:
                raise StreamClosedError(f"{self.name}: closed")
            if self._decoded < i + w:
                assert self._error is not None  # what stopped the decoding short
                raise self._error
            return [self._held[j] for j in range(i, i + w)]

    def release(self, upto: int) -> None:
        """Frames before `upto` are no longer needed (drawn or dropped)."""
        with self._cond:
            for j in range(self._released, min(upto, self._decoded)):
                frame = self._held.pop(j, None)
                if frame is not None:
                    self._spare.append(frame)
            self._released = max(self._released, upto)
            self._cond.notify_all()

    # --- the decoder thread ---

    def _run(self) -> None:
        try:
            with self._cond:
                while not self._turn and not self._closed:
                    self._cond.wait()
            if not self._closed:
                self._decode()
        except Exception as exc:  # VideoError, or a defect: the renderer re-raises it as it is
            with self._cond:
                self._error = exc
        finally:
            with self._cond:
                self._finished = True
                self._cond.notify_all()
                successor = self._next
            if successor is not None:
                successor._give_turn()

    def _decode(self) -> None:
        size = TILES * self.side
        frames = iter_frames(self.data, self.frames, size, size, self.threads, self.codec)
        i = 0
        while True:
            start = time.perf_counter()
            frame: np.ndarray | None = next(frames, None)
            if frame is None:
                return
            decoded = time.perf_counter()
            with self._cond:  # room for one more frame, unless nobody needs this one
                while not self._closed and i >= self._released and len(self._held) >= self.capacity:
                    self._cond.wait()
                if self._closed:
                    return
                keep = i >= self._released
                spare = self._spare.pop() if keep and self._spare else None
            waited = time.perf_counter()
            out = None
            if keep:
                out = dequantize_frame(frame, self.side, self.ranges,
                                       spare if spare is not None else torch.empty(self.side ** 2, FEATURE_DIM),
                                       self.codec.bits)
            done = time.perf_counter()
            with self._cond:
                if out is not None and i >= self._released and not self._closed:
                    self._held[i] = out
                    self.peak_held = max(self.peak_held, len(self._held))
                self._decoded = i + 1
                self.decode_at.append(start)
                self.decode_ms.append((decoded - start) * 1e3)
                self.dequantise_ms.append((done - waited) * 1e3 if keep else 0.0)
                self._cond.notify_all()
            i += 1
