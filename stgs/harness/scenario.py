"""Scenario files (TOML) for `stgs sim` (the traces they name: stgs.harness.trace).

```toml
scene = "dash/"              # a packaged scene folder, or its MPD URL
compare = ["dash-format1/"]  # optional: other trees of the same scene (e.g. format 1 vs 2), one report
abr = ["mpc", "dynamic", "throughput"]   # rules: mpc dynamic throughput bola bola-e
buffer_s = 6.0               # optional (default: three GOPs)
start_s = 0.0                # optional
duration_s = 10.0            # optional (default: to the end)
seed = 0                     # optional
codec = "auto"               # optional: the feature set played where the tree has two (auto | hevc | av1)

[decode]                     # optional: what the player's decoding costs (default: nothing)
keyframe_ms = 120            # keyframe decode per GOP (`stgs play --log` measures it: keyframe_decode_s)
frame_ms = 4.5               # feature frame decode + dequantise (decode_ms + dequantise_ms in the log)
# frame_ms = { qp16 = 6.1, qp24 = 4.5, qp32 = 3.2 }  # or per Representation: decode cost follows the bitrate
# frame_ms = { hevc = 5.0, av1 = 3.0, av1q11 = 3.6 }  # or per codec (a Representation's own entry wins)
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

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from stgs.client.abr import RULES
from stgs.errors import StgsError
from stgs.harness.decode import DecodeSpec, parse_decode
from stgs.harness.trace import TRACE_FORMATS, Trace, constant, load_trace, steps
from stgs.mpd.profile import FEATURE_CODEC_CHOICES
from stgs.tree import MANIFEST

EFFECTS = ("bandwidth", "latency_ms", "jitter_ms", "loss", "outages", "competing", "faults")


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
    """Pin one ladder point (HEVC QP, AV1 QP) instead of adapting (abr ignored)."""
    codec: str = "auto"
    """Feature set the player plays where the tree offers two: auto (HEVC where present), hevc or av1."""
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
                 "codec", "name"}


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
        assert value is not None  # the key is there
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
    codec = doc.get("codec", "auto")
    if codec not in FEATURE_CODEC_CHOICES:
        raise StgsError(f"{where}: 'codec' must be one of {', '.join(FEATURE_CODEC_CHOICES)}, got {codec!r}")
    return Scenario(name=str(doc.get("name") or Path(where).stem), scene=scene, abr=list(abr),
                    buffer_s=_number(doc, "buffer_s", where, 1e-3), start_s=_number(doc, "start_s", where) or 0.0,
                    duration_s=_number(doc, "duration_s", where, 1e-3), seed=int(_number(doc, "seed", where,
                                                                                         integer=True) or 0),
                    decode=parse_decode(doc.get("decode", {}), where),
                    effects=parse_effects(doc.get("effects", {}), where, base), qp=None if qp is None else int(qp),
                    codec=codec, compare=[resolve(c) for c in compare])
