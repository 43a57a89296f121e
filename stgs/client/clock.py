"""The player's presentation clock and buffer level (shared with the harness's simulator).

GOP k is due `(k - k0) * T` after the first frame plus the stalls so far; the
playhead follows the clock but never leaves the GOP being played (it waits at
that GOP's end during a stall). The buffer level is the media downloaded
ahead of the playhead; the fetcher starts another GOP only while it fits.
`now` is whatever clock the caller runs on: wall time in the player,
virtual time in the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

STALL_EPSILON_S = 1e-3
"""A GOP ready less than this after its due time did not stall."""
RENDER_AHEAD = 2
"""Default frame slots the renderer may work ahead of a frame's due time (the first frame of a GOP that
stalled is shown that many slots after it is ready; of the first GOP, at least that many)."""


@dataclass
class PlaybackClock:
    segment_s: float
    """T: the duration of one GOP."""
    capacity_s: float
    """Most media seconds downloaded ahead of the playhead."""
    first_gop: int
    """k0: the GOP playback starts at."""
    t0: float | None = None
    """When the first frame was shown (None: still starting up)."""
    stall_total: float = 0.0
    playing: int = 0
    """The GOP being played (k0 before the start)."""
    fetched_end: int = 0
    """One past the last GOP downloaded."""

    def __post_init__(self) -> None:
        self.playing = max(self.playing, self.first_gop)
        self.fetched_end = max(self.fetched_end, self.first_gop)

    def playhead_s(self, now: float) -> float:
        """Media seconds played since the start."""
        if self.t0 is None:
            return 0.0
        lo = (self.playing - self.first_gop) * self.segment_s
        return min(max(now - self.t0 - self.stall_total, lo), lo + self.segment_s)

    def buffer_level(self, now: float) -> float:
        return max(0.0, (self.fetched_end - self.first_gop) * self.segment_s - self.playhead_s(now))

    def has_room(self, now: float) -> bool:
        """Whether one more GOP fits in the buffer."""
        return self.buffer_level(now) + self.segment_s <= self.capacity_s + 1e-6

    def due(self, k: int) -> float:
        """When GOP k should start (after the first frame)."""
        assert self.t0 is not None, "the clock starts with the first frame"
        return self.t0 + self.stall_total + (k - self.first_gop) * self.segment_s

    def start_time(self, k: int, ready: float, arrived: float, lead: float = 0.0) -> float:
        """When GOP k would start: it became ready at `ready` and the player reached it at `arrived`. The first
        GOP, and one not ready in time (a stall), start `lead` after they are ready: the renderer's head start
        (stgs.client.framepath); one ready in time starts when it is due."""
        if self.t0 is None:
            return ready + lead
        due = max(self.due(k), arrived)
        return ready + lead if ready - due > STALL_EPSILON_S else due

    def start(self, k: int, ready: float, arrived: float, lead: float = 0.0) -> float:
        """GOP k starts playing (see start_time). Returns the stall it caused (0 when it was ready in time)."""
        begin = self.start_time(k, ready, arrived, lead)
        self.playing = k
        if self.t0 is None:
            self.t0 = begin
            return 0.0
        stall = begin - max(self.due(k), arrived)
        if stall > STALL_EPSILON_S:
            self.stall_total += stall
            return stall
        return 0.0
