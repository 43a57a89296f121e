"""Scenario files (TOML) and network traces for `stgs sim`.

```toml
scene = "dash/"              # a packaged scene folder, or its MPD URL
compare = ["dash-format1/"]  # optional: other trees of the same scene (e.g. format 1 vs 2), one report
abr = ["mpc", "dynamic", "throughput"]   # rules: mpc dynamic throughput bola bola-e
buffer_s = 6.0               # optional (default: three GOPs)
start_s = 0.0                # optional
duration_s = 10.0            # optional (default: to the end)
seed = 0                     # optional

[decode]                     # optional: what the player's decoding costs (default: nothing)
keyframe_ms = 120            # keyframe decode per GOP (`stgs play --log` measures it: keyframe_decode_s)
frame_ms = 4.5               # feature frame decode + dequantise (decode_ms + dequantise_ms in the log)
# frame_ms = { qp16 = 6.1, qp24 = 4.5, qp32 = 3.2 }  # or per Representation: decode cost follows the bitrate
ring_frames = 8              # the player's ring of decoded feature frames
render_ahead = 2             # frame slots the player may render a frame early (`stgs play --render-ahead`)

[effects]                    # only the effects named here are simulated
bandwidth = { kbps = 5000 }                          # constant
# bandwidth = { steps = [[0, 5000], [4, 800]] }      # (from second, kbit/s)
# bandwidth = { trace = "traces/bus.log", format = "mahimahi" }   # sabre | mahimahi | pensieve | csv
latency_ms = 40              # round trip per request
jitter_ms = 10               # uniform ± per request
loss = 0.01                  # packet loss probability: its effect on transfer time
outages = [[3.0, 4.5]]       # no bandwidth in these intervals (seconds)
competing = 2                # K other clients share the bottleneck fairly
faults = [{ path = "qp16/seg_00001", status = 503, times = 2 }]   # answer matching requests with an HTTP error
```
"""

from __future__ import annotations

import bisect
import csv
import dataclasses
import io
import itertools
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from stgs.client.abr import RULES
from stgs.errors import StgsError
from stgs.harness.decode import DecodeSpec, parse_decode
from stgs.limits import MAX_TRACE_POINTS
from stgs.tree import MANIFEST

EFFECTS = ("bandwidth", "latency_ms", "jitter_ms", "loss", "outages", "competing", "faults")
TRACE_FORMATS = ("sabre", "mahimahi", "pensieve", "csv")
MAHIMAHI_PACKET_BITS = 1500 * 8
"""A Mahimahi trace line is one delivery opportunity for a 1500-byte packet."""
MAHIMAHI_BIN_S = 0.1
"""Mahimahi packet times are turned into a piecewise-constant rate over bins this long."""


@dataclass
class Trace:
    """Piecewise-constant bandwidth: `kbps[i]` from `times[i]` to the next time; loops after `period`."""

    times: list[float]
    kbps: list[float]
    period: float
    """Seconds after which the trace repeats (math.inf: the last value holds forever)."""
    source: str = ""

    def __post_init__(self) -> None:
        if not self.times:
            raise StgsError(f"{self.source or 'bandwidth'}: the trace is empty")
        if any(not math.isfinite(v) or v < 0 for v in self.kbps):
            raise StgsError(f"{self.source or 'bandwidth'}: bandwidth must be finite and non-negative")
        if any(b <= a for a, b in zip(self.times, self.times[1:], strict=False)) or self.times[0] != 0:
            raise StgsError(f"{self.source or 'bandwidth'}: times must start at 0 and increase")
        ends = [*self.times[1:], self.period]
        if math.isfinite(self.period) and sum(k * (e - s) for s, e, k in zip(self.times, ends, self.kbps,
                                                                              strict=True)) == 0:
            raise StgsError(f"{self.source or 'bandwidth'}: the trace never delivers a byte")

    def segment(self, t: float) -> tuple[float, float]:
        """(kbit/s, seconds until the bandwidth next changes) at time t."""
        if math.isfinite(self.period):
            base = math.floor(t / self.period) * self.period
            local = t - base
        else:
            base, local = 0.0, t
        i = bisect.bisect_right(self.times, local) - 1
        end = self.times[i + 1] if i + 1 < len(self.times) else self.period
        return self.kbps[i], max(end - local, 1e-9) if math.isfinite(end) else math.inf


def constant(kbps: float) -> Trace:
    return Trace([0.0], [float(kbps)], math.inf, source="constant bandwidth")


def steps(points: list) -> Trace:
    try:
        times, rates = zip(*[(float(t), float(k)) for t, k in points], strict=True)
    except (TypeError, ValueError):
        raise StgsError("bandwidth steps must be a list of [second, kbit/s] pairs") from None
    return Trace(list(times), list(rates), math.inf, source="bandwidth steps")


def sniff_format(path: Path, text: str) -> str:
    """The format of a trace file: by suffix (.json Sabre, .csv CSV), else by its first data line: one integer
    (Mahimahi packet times) or two numbers (Pensieve)."""
    suffix = Path(path).suffix
    if suffix in (".json", ".csv"):
        return "sabre" if suffix == ".json" else "csv"
    for line in text.splitlines():
        if line.strip() and not line.startswith("#"):
            return "mahimahi" if len(line.split()) == 1 else "pensieve"
    return "mahimahi"


def load_trace(path: Path, fmt: str | None = None) -> Trace:
    """A trace file (it loops over its own length):
    - `sabre`: Sabre's JSON list of {duration_ms, bandwidth_kbps, latency_ms};
    - `mahimahi`: Mahimahi's own format, one line per 1500-byte delivery opportunity with its time in ms
      (the trace repeats after its last time), turned into a rate per 100-ms bin;
    - `pensieve`: Pensieve's two columns, seconds and Mbit/s;
    - `csv`: named columns time_s, bandwidth_kbps (optional latency_ms, not applied).
    `fmt` None: sniffed (`sniff_format`)."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise StgsError(f"{path}: cannot read trace ({exc})") from None
    fmt = fmt or sniff_format(path, text)
    if fmt not in TRACE_FORMATS:
        raise StgsError(f"{path}: unknown trace format {fmt!r}; known: {', '.join(TRACE_FORMATS)}")
    try:
        if fmt == "sabre":
            rows = json.loads(text)
            if not isinstance(rows, list):
                raise ValueError("a Sabre trace is a JSON list")
            durations = [float(r["duration_ms"]) / 1e3 for r in rows]
            rates = [float(r["bandwidth_kbps"]) for r in rows]
            if any(d <= 0 for d in durations):
                raise ValueError("duration_ms must be positive")
            # latency_ms of a Sabre trace is not applied: only the scenario's own latency_ms effect is
            times = [sum(durations[:i]) for i in range(len(durations))]
            return Trace(times, rates, sum(durations), str(path))
        if fmt == "csv":
            reader = csv.DictReader(io.StringIO(text))
            if not reader.fieldnames or not {"time_s", "bandwidth_kbps"} <= set(reader.fieldnames):
                raise ValueError("columns time_s and bandwidth_kbps are required")
            rows = _bounded(list(reader), path)
            times = [float(r["time_s"]) for r in rows]
            rates = [float(r["bandwidth_kbps"]) for r in rows]
        else:
            lines = _bounded([line.split() for line in text.splitlines()
                              if line.strip() and not line.startswith("#")], path)
            if fmt == "mahimahi":
                return _mahimahi(lines, str(path))
            if any(len(p) != 2 for p in lines):
                hint = " (one number per line is Mahimahi's format)" if lines and len(lines[0]) == 1 else ""
                raise ValueError(f"every line must hold two numbers: seconds and Mbit/s{hint}")
            times = [float(p[0]) for p in lines]
            rates = [float(p[1]) * 1e3 for p in lines]
    except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
        raise StgsError(f"{path}: malformed {fmt} trace ({exc})") from None
    if not times:
        raise StgsError(f"{path}: the trace is empty")
    if times[0] != 0:
        shift = times[0]
        times = [t - shift for t in times]
    step = times[-1] - times[-2] if len(times) > 1 else 1.0
    return Trace(times, rates, times[-1] + step, source=str(path))


def _bounded(points: list, path: Path) -> list:
    """The trace's points, refused past MAX_TRACE_POINTS before any is parsed."""
    if len(points) > MAX_TRACE_POINTS:
        raise StgsError(f"{path}: more than {MAX_TRACE_POINTS} points")
    return points


def _mahimahi(lines: list[list[str]], source: str) -> Trace:
    """Packet delivery times (ms, non-decreasing) -> kbit/s per MAHIMAHI_BIN_S bin, looping after the last time."""
    if any(len(p) != 1 for p in lines):
        hint = " (two columns, seconds and Mbit/s, is Pensieve's format)" if lines and len(lines[0]) == 2 else ""
        raise ValueError(f"every line must hold one integer: a packet's delivery time in ms{hint}")
    ms = [int(p[0]) for p in lines]
    if not ms:
        raise ValueError("no packet times")
    if any(t < 0 for t in ms) or any(b < a for a, b in itertools.pairwise(ms)):
        raise ValueError("packet times must be non-negative and non-decreasing")
    longest_ms = MAX_TRACE_POINTS * MAHIMAHI_BIN_S * 1e3
    if ms[-1] > longest_ms:
        raise ValueError(f"a packet time past {longest_ms:.0f} ms: more than {MAX_TRACE_POINTS} bins of "
                         f"{MAHIMAHI_BIN_S:g} s")
    period = ms[-1] / 1e3
    if period <= 0:
        raise ValueError("the last packet time must be above 0 ms (it is the trace's length)")
    bins = math.ceil(period / MAHIMAHI_BIN_S - 1e-9)
    counts = [0] * bins
    for t in ms:
        counts[min(int(t / 1e3 / MAHIMAHI_BIN_S), bins - 1)] += 1
    times = [i * MAHIMAHI_BIN_S for i in range(bins)]
    widths = [min(MAHIMAHI_BIN_S, period - t) for t in times]
    kbps = [c * MAHIMAHI_PACKET_BITS / w / 1e3 for c, w in zip(counts, widths, strict=True)]
    return Trace(times, kbps, period, source)


@dataclass
class Effects:
    """The network effects a scenario names; anything left None is not simulated at all."""

    bandwidth: Trace | None = None
    latency_ms: float | None = None
    jitter_ms: float | None = None
    loss: float | None = None
    outages: list[tuple[float, float]] | None = None
    competing: int | None = None
    faults: list[Fault] | None = None

    def active(self) -> list[str]:
        return [name for name in EFFECTS if getattr(self, name) is not None]

    def describe(self) -> dict:
        out = {}
        for name in self.active():
            value = getattr(self, name)
            out[name] = value.source if isinstance(value, Trace) else (
                [dataclasses.asdict(f) for f in value] if name == "faults" else value)
        return out


@dataclass
class Fault:
    """Segment requests whose path contains `path` are answered with HTTP `status`, the first `times` of them
    (None: all); 408/429/5xx make the player retry, any other status is final for that segment."""

    path: str
    status: int
    times: int | None = None


def parse_faults(spec: object, where: str) -> list[Fault]:
    if not isinstance(spec, list) or not all(isinstance(f, dict) for f in spec):
        raise StgsError(f"{where}: 'faults' must be a list of tables with path, status and optional times")
    faults = []
    for f in spec:
        extra = sorted(set(f) - {"path", "status", "times"})
        if extra or not isinstance(f.get("path"), str) or not f["path"]:
            raise StgsError(f"{where}: every fault needs a non-empty 'path' (and only path, status, times)")
        status = _number(f, "status", f"{where}: fault", 400, integer=True)
        if status is None or status > 599:
            raise StgsError(f"{where}: a fault's 'status' must be an HTTP error status (400..599)")
        times = _number(f, "times", f"{where}: fault", 1, integer=True)
        faults.append(Fault(f["path"], int(status), None if times is None else int(times)))
    return faults


@dataclass
class Scenario:
    name: str
    scene: str
    """Packaged scene folder or MPD URL."""
    abr: list[str] = field(default_factory=lambda: ["mpc"])
    buffer_s: float | None = None
    start_s: float = 0.0
    duration_s: float | None = None
    seed: int = 0
    decode: DecodeSpec = field(default_factory=DecodeSpec)
    """What the player's decoding costs (stgs.harness.decode)."""
    effects: Effects = field(default_factory=Effects)
    qp: int | None = None
    """Pin one QP instead of adapting (abr ignored)."""
    compare: list[str] = field(default_factory=list)
    """Other packaged trees (folders or MPD URLs) played under the same settings, reported beside `scene`."""
    label: str = ""
    """The tree's short name in a report that compares several (set by `variants`)."""

    def variants(self) -> list[Scenario]:
        """This scenario once per tree (`scene`, then each of `compare`), named after the tree when there are
        several."""
        scenes = [self.scene, *self.compare]
        if len(scenes) == 1:
            return [dataclasses.replace(self, label=scene_labels(scenes)[0])]
        return [dataclasses.replace(self, scene=s, compare=[], name=f"{self.name}-{label}", label=label)
                for s, label in zip(scenes, scene_labels(scenes), strict=True)]


def scene_labels(scenes: list[str]) -> list[str]:
    """Short distinct names of trees: each folder's name (the MPD's folder for a URL), with as many parent
    folders as it takes to tell them apart (then a number)."""
    parts = [[p for p in (s[:-len(MANIFEST)] if s.endswith(MANIFEST) else s).split("/") if p] or ["scene"]
             for s in scenes]
    for depth in range(1, max(len(p) for p in parts) + 1):
        labels = ["/".join(p[-depth:]) for p in parts]
        if len(set(labels)) == len(labels):
            return labels
    return [f"{label}-{i}" for i, label in enumerate(labels)]


SCENARIO_KEYS = {"scene", "compare", "abr", "buffer_s", "start_s", "duration_s", "seed", "decode", "effects", "qp",
                 "name"}


def _number(doc: dict, key: str, where: str, lo: float = 0.0, integer: bool = False) -> float | None:
    if key not in doc:
        return None
    value = doc[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        raise StgsError(f"{where}: '{key}' must be a{'n integer' if integer else ' number'}, got {value!r}")
    if not math.isfinite(value) or value < lo:
        raise StgsError(f"{where}: '{key}' must be >= {lo}, got {value}")
    return value


def parse_effects(doc: object, where: str, base: Path) -> Effects:
    if not isinstance(doc, dict):
        raise StgsError(f"{where}: [effects] must be a table")
    unknown = sorted(set(doc) - set(EFFECTS))
    if unknown:
        raise StgsError(f"{where}: unknown effect(s) {unknown}; known: {', '.join(EFFECTS)}")
    fx = Effects()
    if "bandwidth" in doc:
        fx.bandwidth = parse_bandwidth(doc["bandwidth"], where, base)
    fx.latency_ms = _number(doc, "latency_ms", where)
    fx.jitter_ms = _number(doc, "jitter_ms", where)
    fx.loss = _number(doc, "loss", where)
    if fx.loss is not None and fx.loss >= 1:
        raise StgsError(f"{where}: 'loss' must be below 1, got {fx.loss}")
    competing = _number(doc, "competing", where, integer=True)
    fx.competing = int(competing) if competing is not None else None
    if "faults" in doc:
        fx.faults = parse_faults(doc["faults"], where)
    if "outages" in doc:
        try:
            fx.outages = [(float(a), float(b)) for a, b in doc["outages"]]
        except (TypeError, ValueError):
            raise StgsError(f"{where}: 'outages' must be a list of [start, end] seconds") from None
        if any(not (0 <= a < b) for a, b in fx.outages):
            raise StgsError(f"{where}: every outage needs 0 <= start < end")
    return fx


def parse_bandwidth(spec: object, where: str, base: Path) -> Trace:
    if not isinstance(spec, dict) or len({"kbps", "steps", "trace"} & set(spec)) != 1:
        raise StgsError(f"{where}: bandwidth is a table with one of kbps, steps or trace")
    extra = sorted(set(spec) - {"kbps", "steps", "trace", "format"})
    if extra:
        raise StgsError(f"{where}: unknown bandwidth key(s) {extra}")
    if "kbps" in spec:
        value = _number(spec, "kbps", where)
        return constant(value)
    if "steps" in spec:
        return steps(spec["steps"])
    fmt = spec.get("format")
    if fmt is not None and not isinstance(fmt, str):
        raise StgsError(f"{where}: a trace's 'format' is one of {', '.join(TRACE_FORMATS)}")
    return load_trace(base / str(spec["trace"]), fmt)


def load_scenario(path: Path) -> Scenario:
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise StgsError(f"{path}: cannot read scenario ({exc})") from None
    return scenario_from_dict(doc, str(path), path.parent)


def scenario_from_dict(doc: dict, where: str, base: Path) -> Scenario:
    unknown = sorted(set(doc) - SCENARIO_KEYS)
    if unknown:
        raise StgsError(f"{where}: unknown key(s) {unknown}; known: {', '.join(sorted(SCENARIO_KEYS))}")
    if not isinstance(doc.get("scene"), str):
        raise StgsError(f"{where}: 'scene' (a packaged scene folder or MPD URL) is required")
    compare = doc.get("compare", [])
    if not isinstance(compare, list) or any(not isinstance(c, str) for c in compare):
        raise StgsError(f"{where}: 'compare' must list packaged scene folders or MPD URLs")

    def resolve(scene: str) -> str:
        return scene if scene.startswith(("http://", "https://")) else str((base / scene).resolve())

    scene = resolve(doc["scene"])
    abr = doc.get("abr", ["mpc"])
    abr = [abr] if isinstance(abr, str) else abr
    if not isinstance(abr, list) or not abr or any(not isinstance(a, str) or a not in RULES for a in abr):
        raise StgsError(f"{where}: 'abr' must list rules from {', '.join(RULES)}, got {abr!r}")
    qp = _number(doc, "qp", where, integer=True)
    return Scenario(name=str(doc.get("name") or Path(where).stem), scene=scene, abr=list(abr),
                    buffer_s=_number(doc, "buffer_s", where, 1e-3), start_s=_number(doc, "start_s", where) or 0.0,
                    duration_s=_number(doc, "duration_s", where, 1e-3), seed=int(_number(doc, "seed", where,
                                                                                         integer=True) or 0),
                    decode=parse_decode(doc.get("decode", {}), where),
                    effects=parse_effects(doc.get("effects", {}), where, base), qp=None if qp is None else int(qp),
                    compare=[resolve(c) for c in compare])
