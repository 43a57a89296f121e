"""Fuzzing the parsers that read what the network or a user hands us: the targets and the harness that runs them.

Targets (each a function of the fuzzed input, with the one error type it may raise; their inputs:
`stgs.testing.fuzz_inputs`):

- `mpd`: the MPD model and the client's Presentation (URLs, spans, caps) on a StreamSTGS MPD whose attribute
  values are drawn (huge numbers, odd durations, template widths, junk) or whose bytes are mutated; MPDError.
  The MPD may carry a static-layer AdaptationSet (format 2) with a drawn descriptor; one that lost its keyframe set
  to a mutation is read as a still scene (StillPresentation).
- `keyframe`: the keyframe reader on a real keyframe segment with its safetensors header's fields replaced by
  drawn JSON values or its bytes mutated; KeyframeError.
- `static`: the static-layer reader on a real static segment (with view-dependent colour) edited the same
  ways; StaticSegmentError.
- `mp4`: the ISO BMFF box code (split, timeline read/write, track timescale, codecs string) on a real HEVC
  fragment with mutated bytes; MP4Error.
- `trace`, `scenario`: the harness's trace formats and scenario files on drawn text; StgsError.

Any other exception, a case running past its alarm, or memory growing past the bound is a finding. The test
suite runs each target for a few hundred derandomised cases (tests/fuzz); `python -m bench.fuzzing.fuzz` runs them
for as long as asked, with fresh random cases, and reports cases per second (docs/SECURITY.md, "Fuzzing").
"""

from __future__ import annotations

import contextlib
import resource
import signal
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from stgs.client.manifest import StillPresentation, open_presentation
from stgs.codec.keyframe import KeyframeError, decode_keyframe
from stgs.codec.mp4 import MP4Error, hevc_codecs, media_timeline, set_timeline, split_fragmented, track_timescale
from stgs.codec.static import StaticSegmentError, decode_static
from stgs.errors import MPDError, StgsError
from stgs.harness.scenario import load_scenario
from stgs.harness.trace import load_trace
from stgs.testing.fuzz_inputs import (
    STATIC_SEED_CAPACITY,
    header_edits,
    mpd_inputs,
    mutated,
    scenario_inputs,
    seed_fragment,
    seed_keyframe,
    seed_static,
    trace_inputs,
)

CASE_ALARM_S = 5.0
"""A case that runs longer than this hangs (every target takes milliseconds on honest input)."""
MEMORY_BOUND_MB = 1024
"""Peak RSS growth a fuzz run may cause."""


class HangError(Exception):
    """A case ran past its alarm."""


@contextlib.contextmanager
def alarm(seconds: float) -> Iterator[None]:
    def ring(signum: int, frame: object) -> None:
        raise HangError(f"a case ran past {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, ring)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# --- targets ---

def mpd_target(data: bytes) -> None:
    pres = open_presentation(data, "http://example.com/scene/manifest.mpd")
    if isinstance(pres, StillPresentation):  # a still scene: the static layer alone
        pres.static_url(), pres.max_static_bytes()
        return
    last = pres.ladder[-1].rep_id
    pres.keyframe_url(0), pres.init_url(last), pres.media_url(last, pres.num_gops - 1)
    pres.span(0.0, None, None), pres.span(pres.duration / 2, 1.0, 5.0), pres.gop_at(pres.duration)
    pres.max_keyframe_bytes(), pres.max_media_bytes(last), pres.decoded_gop_bytes(8)
    if pres.static is not None:
        pres.static_url(), pres.max_static_bytes(), pres.static_layer_bytes()


def keyframe_target(data: bytes) -> None:
    _, shape = seed_keyframe()
    decode_keyframe(data, shape, 1, 1 << 20)


def static_target(data: bytes) -> None:
    decode_static(data, STATIC_SEED_CAPACITY, 1, 1 << 20)


def mp4_target(data: bytes) -> None:
    init, media = split_fragmented(data)
    hevc_codecs(init), track_timescale(init)
    media_timeline(set_timeline(media, 7, 12345))


def trace_target(case: tuple[str | None, str]) -> None:
    fmt, text = case
    with tempfile.NamedTemporaryFile("w", suffix=".trace") as f:
        f.write(text)
        f.flush()
        load_trace(Path(f.name), fmt)


def scenario_target(text: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.toml"
        path.write_text(text, errors="replace")
        load_scenario(path)


@dataclass(frozen=True)
class Target:
    inputs: Callable[[], st.SearchStrategy]
    run: Callable[[Any], None]
    """Runs one case drawn from `inputs`."""
    allowed: type[BaseException]
    """The one error type the target may raise."""


TARGETS = {
    "mpd": Target(mpd_inputs, mpd_target, MPDError),
    "keyframe": Target(lambda: st.one_of(header_edits(seed_keyframe()[0]), mutated(seed_keyframe()[0])),
                       keyframe_target, KeyframeError),
    "static": Target(lambda: st.one_of(header_edits(seed_static()), mutated(seed_static())), static_target,
                     StaticSegmentError),
    "mp4": Target(lambda: mutated(seed_fragment()), mp4_target, MP4Error),
    "trace": Target(trace_inputs, trace_target, StgsError),
    "scenario": Target(scenario_inputs, scenario_target, StgsError),
}


def check(target: Target, case: object) -> None:
    """Run one case: only the target's own error type may escape, within the alarm."""
    with alarm(CASE_ALARM_S), contextlib.suppress(target.allowed):
        target.run(case)


def fuzz(name: str, examples: int, derandomize: bool) -> int:
    """Run `examples` cases of target `name`; returns how many ran (a finding raises)."""
    target = TARGETS[name]
    count = [0]

    @settings(max_examples=examples, deadline=None, database=None, derandomize=derandomize,
              phases=[Phase.generate, Phase.shrink], suppress_health_check=list(HealthCheck))
    @given(target.inputs())
    def run(case: object) -> None:
        count[0] += 1
        check(target, case)

    run()
    return count[0]
