"""Fuzzing the parsers that read what the network or a user hands us (`python -m bench.fuzz`).

Targets (each a function of the fuzzed input, with the one error type it may raise):

- `mpd`: the MPD model and the client's Presentation (URLs, spans, caps) on a StreamSTGS MPD whose attribute
  values are drawn (huge numbers, odd durations, template widths, junk) or whose bytes are mutated; MPDError.
  The MPD may carry a static-layer AdaptationSet (format 2) with a drawn descriptor.
- `keyframe`: the keyframe reader on a real keyframe segment with its safetensors header's fields replaced by
  drawn JSON values or its bytes mutated; KeyframeError.
- `static`: the static-layer reader on a real static segment (with view-dependent colour) edited the same
  ways; StaticSegmentError.
- `mp4`: the ISO BMFF box code (split, timeline read/write, track timescale, codecs string) on a real HEVC
  fragment with mutated bytes; MP4Error.
- `trace`, `scenario`: the harness's trace formats and scenario files on drawn text; StgsError.

Any other exception, a case running past its alarm, or memory growing past the bound is a finding. The test
suite runs each target for a few hundred derandomised cases (tests/fuzz); this module runs them for as long as
asked, with fresh random cases, and reports cases per second.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import resource
import signal
import struct
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from stgs.client.manifest import Presentation
from stgs.codec.features import feature_ranges
from stgs.codec.keyframe import KeyframeError, decode_keyframe, encode_keyframe
from stgs.codec.mp4 import MP4Error, hevc_codecs, media_timeline, set_timeline, split_fragmented, track_timescale
from stgs.codec.static import StaticSegmentError, decode_static, encode_static
from stgs.codec.video import VideoTiming, encode_gop
from stgs.errors import StgsError
from stgs.harness.scenario import load_scenario
from stgs.harness.trace import load_trace
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.static import StaticLayer
from stgs.mpd import MPDError, parse_mpd

CASE_ALARM_S = 5.0
"""A case that runs longer than this hangs (every target takes milliseconds on honest input)."""
MEMORY_BOUND_MB = 1024
"""Peak RSS growth a fuzz run may cause."""

SEED_MPD = """<?xml version='1.0' encoding='UTF-8'?>
<MPD xmlns="urn:mpeg:dash:schema:mpd:2011" type="static" profiles="urn:mpeg:dash:profile:isoff-live:2011,\
urn:streamstgs:profile:2026" mediaPresentationDuration="{duration}" minBufferTime="PT1S">{base}
  <Period id="0" start="PT0S">{static}
    <AdaptationSet id="1" contentType="application" mimeType="application/vnd.streamstgs.keyframe">
      <SupplementalProperty schemeIdUri="urn:streamstgs:keyframe:2026" value="{params}"/>
      <SegmentTemplate media="{kf_media}" timescale="{timescale}" duration="{seg_duration}" startNumber="{start}"/>
      <Representation id="keyframes" bandwidth="{kf_bandwidth}"/>
    </AdaptationSet>
    <AdaptationSet id="2" contentType="video" mimeType="video/mp4">
      <SupplementalProperty schemeIdUri="urn:streamstgs:features:2026" value="tiles=4x4;channels=16;bits=12"/>
      <SegmentTemplate media="{media}" timescale="{timescale}" duration="{seg_duration}" startNumber="{start}"
        initialization="v-1/features/$RepresentationID$/init.mp4"/>
      <Representation id="{rep_id}" bandwidth="{bandwidth}" codecs="hvc1.4.10.L60.99.C8" width="256" height="256"/>
      <Representation id="qp32" bandwidth="677024" codecs="hvc1.4.10.L60.99.C8" width="256" height="256"/>
    </AdaptationSet>
  </Period>
</MPD>"""

STATIC_SET = """
    <AdaptationSet id="0" contentType="application" mimeType="application/vnd.streamstgs.static">
      <SupplementalProperty schemeIdUri="urn:streamstgs:static:2026" value="{static_params}"/>
      <SegmentTemplate media="{static_media}" timescale="1024" duration="2048" startNumber="0"/>
      <Representation id="static" bandwidth="{static_bandwidth}"/>
    </AdaptationSet>"""
"""A format-2 MPD's static-layer AdaptationSet (SEED_MPD's `static`, empty in format 1)."""
STATIC_VALUES = {"static_params": "version=1;capacity=1024;grid_side=32;sh_degree=0",
                 "static_media": "v-1/static/layer.stgl", "static_bandwidth": "32676"}

SEED_VALUES = {"duration": "PT2S", "base": "", "static": "",
               "params": "version=1;capacity=4096;grid_side=64;gop_size=30;window=3;pe_freqs=4;fps=30",
               "kf_media": "v-1/keyframes/gop_$Number%05d$.stgk", "timescale": "1024", "seg_duration": "1024",
               "start": "0", "kf_bandwidth": "974904",
               "media": "v-1/features/$RepresentationID$/seg_$Number%05d$.m4s", "rep_id": "qp16",
               "bandwidth": "6387080"}


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


# --- strategies ---

def numbers() -> st.SearchStrategy[str]:
    return st.one_of(st.integers().map(str), st.integers(0, 500).map(lambda n: "9" * max(n, 1)),
                     st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(max_size=12))


def durations() -> st.SearchStrategy[str]:
    return st.one_of(numbers().map(lambda n: f"PT{n}S"), numbers().map(lambda n: f"P{n}D"),
                     st.integers(0, 6000).map(lambda n: "P" + "9" * n + "DT1S"), st.text(max_size=20))


def templates() -> st.SearchStrategy[str]:
    widths = st.one_of(st.integers(0, 40), st.integers(), st.just(10**30)).map(str)
    return st.one_of(widths.map(lambda w: f"x/$Number%0{w}d$.m4s"), st.text(max_size=40),
                     st.sampled_from(["$$$", "$Number$", "$RepresentationID$$Number%d$", "$Time$", "../../x"]))


def descriptor_values(keys: list[str]) -> st.SearchStrategy[str]:
    """A descriptor's `key=value;...` value with some of `keys`, each given a drawn number."""
    return st.dictionaries(st.sampled_from(keys), numbers(), max_size=len(keys)).map(
        lambda d: ";".join(f"{k}={v}" for k, v in d.items()))


def static_sets() -> st.SearchStrategy[str]:
    """A static-layer AdaptationSet with drawn descriptor fields, template and bandwidth."""
    params = descriptor_values(["version", "capacity", "grid_side", "sh_degree", "junk"])
    drawn = {"static_params": st.one_of(st.just(STATIC_VALUES["static_params"]), params),
             "static_media": templates(), "static_bandwidth": numbers()}
    return st.fixed_dictionaries({}, optional=drawn).map(
        lambda d: STATIC_SET.format(**{k: _xml_escape(v) for k, v in {**STATIC_VALUES, **d}.items()}))


def mpd_values() -> st.SearchStrategy[dict[str, str]]:
    params = descriptor_values(["version", "capacity", "grid_side", "gop_size", "window", "pe_freqs", "fps", "junk"])
    drawn = {"duration": durations(), "params": st.one_of(st.just(SEED_VALUES["params"]), params),
             "kf_media": templates(), "media": templates(), "timescale": numbers(), "seg_duration": numbers(),
             "start": numbers(), "kf_bandwidth": numbers(), "bandwidth": numbers(), "rep_id": st.text(max_size=10),
             "base": st.one_of(st.just(""), st.text(max_size=30).map(lambda t: f"<BaseURL>{t}</BaseURL>")),
             "static": st.one_of(st.just(""), static_sets())}
    return st.fixed_dictionaries({}, optional=drawn).map(lambda d: {**SEED_VALUES, **d})


def _xml_escape(value: str) -> str:
    return value.replace("&", "&amp;").replace("<", "&lt;").replace('"', "&quot;")


def mutated(seed: bytes) -> st.SearchStrategy[bytes]:
    """The seed with a few byte edits (overwrite, insert, delete, truncate)."""
    edit = st.tuples(st.sampled_from(["set", "insert", "delete", "truncate"]), st.integers(0, max(0, len(seed) - 1)),
                     st.binary(min_size=1, max_size=8))

    def apply(edits: list) -> bytes:
        data = bytearray(seed)
        for op, pos, blob in edits:
            pos = min(pos, len(data))
            if op == "set":
                data[pos:pos + len(blob)] = blob
            elif op == "insert":
                data[pos:pos] = blob
            elif op == "delete":
                del data[pos:pos + len(blob)]
            else:
                del data[pos:]
        return bytes(data)

    return st.lists(edit, min_size=1, max_size=6).map(apply)


def mpd_inputs() -> st.SearchStrategy[bytes]:
    structured = mpd_values().map(lambda v: SEED_MPD.format(**{k: x if k in ("base", "static") else _xml_escape(x)
                                                               for k, x in v.items()}).encode("utf-8", "replace"))
    layered = {**SEED_VALUES, "static": STATIC_SET.format(**STATIC_VALUES)}
    return st.one_of(structured, mutated(SEED_MPD.format(**SEED_VALUES).encode()),
                     mutated(SEED_MPD.format(**layered).encode()))


def json_values() -> st.SearchStrategy[object]:
    leaves = st.one_of(st.none(), st.booleans(), st.integers(), st.integers(-1, 2**64 + 1),
                       st.floats(allow_nan=True), st.text(max_size=10))
    return st.recursive(leaves, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                        st.dictionaries(st.text(max_size=5), inner, max_size=3)),
                        max_leaves=8)


@functools.cache
def seed_keyframe() -> tuple[bytes, object]:
    torch.manual_seed(0)
    model = GOPModel(GOPShape(capacity=64, gop_size=4, window=2))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.4)
    return encode_keyframe(1, model, feature_ranges(model.features.detach())), model.shape


STATIC_SEED_CAPACITY = 64


@functools.cache
def seed_static() -> bytes:
    """A static segment with degree-1 view-dependent colour (its three extra images included)."""
    torch.manual_seed(0)
    layer = StaticLayer(STATIC_SEED_CAPACITY, sh_degree=1)
    with torch.no_grad():
        for p in layer.parameters():
            p.normal_(0, 0.4)
    return encode_static(layer)


def header_edits(seed: bytes) -> st.SearchStrategy[bytes]:
    """The seed keyframe with one field of its safetensors header (or metadata) replaced by a drawn value."""
    size = struct.unpack_from("<Q", seed)[0]
    header = json.loads(seed[8:8 + size])
    names = sorted(header)

    def apply(choice: tuple[str, str, object]) -> bytes:
        name, key, value = choice
        doc = json.loads(json.dumps(header))
        entry = doc[name]
        if name == "__metadata__":
            meta = json.loads(entry["streamstgs"])
            meta[key if key in meta else "gop"] = value
            entry["streamstgs"] = json.dumps(meta)
        else:
            entry[key] = value
        raw = json.dumps(doc).encode()
        return struct.pack("<Q", len(raw)) + raw + seed[8 + size:]

    return st.tuples(st.sampled_from(names), st.sampled_from(["dtype", "shape", "data_offsets", "capacity", "gop",
                                                             "sh_degree"]),
                     json_values()).map(apply)


@functools.cache
def seed_fragment() -> bytes:
    frames = (np.arange(3 * 64 * 64, dtype=np.uint16).reshape(3, 64, 64) * 7) % 4096
    return encode_gop(frames.astype(np.uint16), 30, VideoTiming.for_gop(3, 2, 30.0), preset="ultrafast")


TRACE_LINES = st.lists(st.one_of(st.tuples(numbers(), numbers()).map(" ".join), numbers(), st.text(max_size=20)),
                       max_size=20).map("\n".join)
PACKET_TIMES = st.lists(st.one_of(st.integers(-10, 10**15).map(str), numbers(), st.text(max_size=8)),
                        max_size=30).map("\n".join)


def trace_inputs() -> st.SearchStrategy[tuple[str | None, str]]:
    sabre = st.lists(st.fixed_dictionaries({}, optional={"duration_ms": json_values(), "bandwidth_kbps":
                                                         json_values(), "latency_ms": json_values()}),
                     max_size=6).map(json.dumps)
    csv = st.lists(st.tuples(numbers(), numbers()).map(",".join), max_size=10).map(
        lambda rows: "\n".join(["time_s,bandwidth_kbps", *rows]))
    return st.one_of(st.tuples(st.just("sabre"), st.one_of(sabre, st.text(max_size=40))),
                     st.tuples(st.just("pensieve"), TRACE_LINES), st.tuples(st.just("mahimahi"), PACKET_TIMES),
                     st.tuples(st.just("csv"), csv), st.tuples(st.none(), st.one_of(TRACE_LINES, PACKET_TIMES)))


def toml_value() -> st.SearchStrategy[str]:
    scalars = st.one_of(st.integers().map(str), st.floats(allow_nan=True).map(
        lambda f: "nan" if math.isnan(f) else "inf" if f == math.inf else "-inf" if f == -math.inf else repr(f)),
        st.text(max_size=10).map(json.dumps), st.booleans().map(lambda b: str(b).lower()))
    return st.one_of(scalars, st.lists(scalars, max_size=4).map(lambda v: "[" + ", ".join(v) + "]"),
                     st.lists(st.lists(scalars, max_size=3).map(lambda v: "[" + ", ".join(v) + "]"),
                              max_size=4).map(lambda v: "[" + ", ".join(v) + "]"))


def scenario_inputs() -> st.SearchStrategy[str]:
    keys = st.sampled_from(["scene", "abr", "qp", "buffer_s", "start_s", "duration_s", "seed", "name", "runs",
                            "speed", "bogus"])
    top = st.dictionaries(keys, toml_value(), max_size=6)
    tables = st.dictionaries(st.sampled_from(["bandwidth", "effects"]), st.dictionaries(
        st.sampled_from(["kbps", "steps", "trace", "format", "rtt_ms", "jitter_ms", "loss", "outages", "faults"]),
        toml_value(), max_size=4), max_size=2)

    def render(parts: tuple[dict, dict]) -> str:
        head, sections = parts
        lines = ['scene = "."', *(f"{k} = {v}" for k, v in head.items() if k != "scene")]
        for name, table in sections.items():
            lines += [f"[{name}]", *(f"{k} = {v}" for k, v in table.items())]
        return "\n".join(lines)

    return st.one_of(st.tuples(top, tables).map(render), st.text(max_size=60))


# --- targets ---

def mpd_target(data: bytes) -> None:
    pres = Presentation(parse_mpd(data), "http://example.com/scene/manifest.mpd")
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
    run: Callable[[object], None]
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=20_000, help="cases per target (default: 20000)")
    parser.add_argument("--target", choices=sorted(TARGETS), action="append", help="only these (repeatable)")
    args = parser.parse_args(argv)
    print("| target | cases | seconds | cases/s | peak RSS growth |\n|---|---|---|---|---|")
    for name in args.target or TARGETS:
        TARGETS[name].inputs()  # builds the target's seeds (an encode, a model) outside the measured growth
        before = peak_rss_mb()
        start = time.perf_counter()
        count = fuzz(name, args.examples, derandomize=False)
        seconds = time.perf_counter() - start
        grown = peak_rss_mb() - before
        print(f"| {name} | {count} | {seconds:.0f} | {count / seconds:.0f} | {grown:.0f} MB |", flush=True)
        if grown > MEMORY_BOUND_MB:
            raise SystemExit(f"{name}: peak RSS grew by {grown:.0f} MB (bound {MEMORY_BOUND_MB} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
