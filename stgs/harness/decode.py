"""The player's decoder on the simulator's virtual clock: keyframes whole, features frame by frame into a ring.

Mirrors stgs.client.gopdecode and stgs.codec.stream, real-time playback with instantaneous rendering:

- GOP k is taken up once it is downloaded, a decode slot is free (at most two GOPs decoded at once) and
  the previous GOP is ready; its keyframe then decodes in `keyframe_s`;
- its feature frames decode one after another, `frame_s` each, beside the keyframe (the player starts
  the feature stream from the keyframe's header), starting once the GOP is taken up and GOP k-1's feature
  decoding has ended; feature frame j waits for room in the ring of `ring` frames, i.e.
  for frame j - ring to be released; decoding ends after the last frame, or when the GOP's playback ends
  (the player closes its stream: the frame being decoded finishes, the rest is never decoded);
- GOP k is ready when its keyframe, the static layer (format 2) and its first window (W frames) are
  decoded: it starts at max(its due time, ready);
- frame m of the GOP is drawn if its window (frames m … m+W-1) is decoded before its slot
  [start + m/fps, start + (m+1)/fps) ends, released when drawn: once its window is decoded, the frame before
  it released, and no earlier than `render_ahead` slots before its own (stgs.client.framepath); otherwise
  it is dropped and released at the slot's end.

With frame_s = 0 a GOP is simply ready keyframe_s after it can be decoded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from stgs.client.clock import RENDER_AHEAD
from stgs.errors import StgsError
from stgs.tree import parse_rep_id

DECODE_KEYS = ("keyframe_ms", "frame_ms", "ring_frames", "render_ahead", "static_ms")


@dataclass(frozen=True)
class DecodeSpec:
    """A scenario's [decode] table: what the simulated player's decoding costs (measure it with `stgs play
    --log`: its per-GOP keyframe_decode_s and per-frame decode_ms + dequantise_ms)."""

    keyframe_ms: float = 0.0
    """Keyframe decode per GOP."""
    frame_ms: float | dict[str, float] = 0.0
    """Feature frame decode + dequantise: one value, or a table by Representation id and/or codec name (`hevc`,
    `av1`: decode cost follows the codec and the bitrate; a Representation's own entry wins)."""
    ring_frames: int = 8
    """The player's ring of feature frames (PlayConfig.ring_frames)."""
    render_ahead: int = 0
    """Frame slots the player may render a frame before its own (PlayConfig.render_ahead): its GOPs start that
    many slots after they are ready at the start and after a stall. A [decode] table defaults to the player's
    default; without one the simulated player neither decodes nor renders (0)."""
    static_ms: float = 0.0
    """A layered scene's static-layer decode, once (the log's static_decode_s): no GOP is ready before the
    static layer is decoded, as in the player."""

    def frame_s(self, rep: str) -> float:
        """Seconds per feature frame of Representation `rep`."""
        if isinstance(self.frame_ms, dict):
            parsed = parse_rep_id(rep)
            key = rep if rep in self.frame_ms or parsed is None else parsed[0]
            if key not in self.frame_ms:
                raise StgsError(f"[decode] frame_ms gives no cost for Representation {rep!r} nor its codec "
                                f"(it lists {', '.join(sorted(self.frame_ms))})")
            return self.frame_ms[key] / 1e3
        return self.frame_ms / 1e3


def _milliseconds(value: object, what: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise StgsError(f"{where}: {what} must be a number of milliseconds >= 0, got {value!r}")
    return float(value)


def parse_decode(doc: object, where: str) -> DecodeSpec:
    if not isinstance(doc, dict):
        raise StgsError(f"{where}: [decode] must be a table")
    unknown = sorted(set(doc) - set(DECODE_KEYS))
    if unknown:
        raise StgsError(f"{where}: unknown decode key(s) {unknown}; known: {', '.join(DECODE_KEYS)}")
    keyframe = _milliseconds(doc.get("keyframe_ms", 0.0), "decode 'keyframe_ms'", where)
    frame = doc.get("frame_ms", 0.0)
    if isinstance(frame, dict):
        frame = {str(rep): _milliseconds(v, f"decode 'frame_ms.{rep}'", where) for rep, v in frame.items()}
    else:
        frame = _milliseconds(frame, "decode 'frame_ms' (or a table by Representation id)", where)
    ring = doc.get("ring_frames", 8)
    if isinstance(ring, bool) or not isinstance(ring, int) or ring < 1:
        raise StgsError(f"{where}: decode 'ring_frames' must be an integer >= 1, got {ring!r}")
    ahead = doc.get("render_ahead", RENDER_AHEAD)
    if isinstance(ahead, bool) or not isinstance(ahead, int) or ahead < 0:
        raise StgsError(f"{where}: decode 'render_ahead' must be an integer >= 0, got {ahead!r}")
    static = _milliseconds(doc.get("static_ms", 0.0), "decode 'static_ms'", where)
    return DecodeSpec(keyframe, frame, ring, ahead, static)


@dataclass(frozen=True)
class GOPPlan:
    """GOP k's decoding before it starts: when its keyframe and its first feature window are decoded."""

    keyframe_done: float
    features_start: float
    frame_s: float
    ready: float
    """When its first window is decoded: the GOP may start."""


@dataclass
class DecoderModel:
    ring: int
    """Feature frames the ring holds (PlayConfig.ring_frames)."""
    window: int
    """W: feature frames one frame reads."""
    gop_size: int
    fps: float
    render_ahead: int = 0
    """Frame slots a frame may be drawn (and its features released) before its own."""
    keyframe_free: float = 0.0
    """When the keyframe decoder is next free."""
    features_free: float = 0.0
    """When the previous GOP's last feature frame is decoded."""

    @property
    def features(self) -> int:
        """E = G + W - 1 feature frames per GOP."""
        return self.gop_size + self.window - 1

    def plan(self, downloaded: float, slot: float, keyframe_s: float, frame_s: float,
             not_before: float = 0.0) -> GOPPlan:
        """The next GOP's decoding: downloaded at `downloaded`, a decode slot free at `slot`, its keyframe
        costing `keyframe_s` and its feature frames `frame_s` each, ready not before `not_before` (the
        static layer decoded); nothing is committed until `start`."""
        taken = max(downloaded, slot, self.keyframe_free)  # the player takes the GOP up
        keyframe_done = taken + keyframe_s
        first = max(taken, self.features_free)  # its features decode beside the keyframe (the other core)
        ready = max(keyframe_done, not_before, first + self.window * frame_s)  # the first window fits the ring
        return GOPPlan(keyframe_done, first, frame_s, ready)

    def start(self, plan: GOPPlan, start: float) -> int:
        """The planned GOP plays from `start`; returns its dropped frames."""
        period = 1.0 / self.fps
        end = start + self.gop_size * period  # the player closes the GOP's stream here
        decoded: list[float] = []
        released: list[float] = []
        t = plan.features_start
        for j in range(self.features):
            room = t if j < self.ring else max(t, self._release(j - self.ring, start, period, decoded, released))
            if room >= end:  # closed while decoding the frame before (it finishes) or waiting for room
                t = max(t, end)
                break
            t = room + plan.frame_s
            decoded.append(t)
        self.keyframe_free = plan.ready  # the player decodes the next keyframe once this GOP is ready
        self.features_free = t
        return sum(1 for m in range(self.gop_size) if not self._drawn(m, start, period, decoded))

    def _drawn(self, m: int, start: float, period: float, decoded: list[float]) -> bool:
        """Whether frame m's window is decoded before its slot ends."""
        last = m + self.window - 1
        return last < len(decoded) and decoded[last] < start + (m + 1) * period

    def _release(self, m: int, start: float, period: float, decoded: list[float], released: list[float]) -> float:
        """When feature frame m is released (computing the releases up to m in order): frame m's slot
        ends, or its window is decoded within the slot and it is drawn; feature frames past the GOP's
        last frame stay until the GOP ends."""
        while len(released) <= m:
            i = len(released)
            if i >= self.gop_size:
                released.append(start + self.gop_size * period)
                continue
            slot_start, slot_end = start + i * period, start + (i + 1) * period
            # frame i's window is decoded already (i + W - 1 < j when the ring holds W)
            drawn = self._drawn(i, start, period, decoded)
            earliest = max(slot_start - self.render_ahead * period, released[-1] if released else 0.0)
            released.append(max(earliest, decoded[i + self.window - 1]) if drawn else slot_end)
        return released[m]
