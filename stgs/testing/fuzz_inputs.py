"""What `stgs.testing.fuzz` feeds its targets: the seed inputs (a StreamSTGS MPD, a keyframe, a static segment, an HEVC
fragment) and the Hypothesis strategies that draw or mutate them."""

from __future__ import annotations

import functools
import json
import math
import struct

import numpy as np
import torch
from hypothesis import strategies as st

from stgs.codec.features import feature_ranges
from stgs.codec.keyframe import encode_keyframe
from stgs.codec.static import encode_static
from stgs.codec.video import VideoTiming, encode_gop
from stgs.model.gop import GOPModel, GOPShape
from stgs.model.static import StaticLayer

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
def seed_keyframe() -> tuple[bytes, GOPShape]:
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
