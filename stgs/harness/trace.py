"""Network traces for `stgs sim`: piecewise-constant bandwidth, read from Sabre, Mahimahi, Pensieve or CSV files."""

from __future__ import annotations

import bisect
import csv
import io
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

from stgs.errors import StgsError
from stgs.limits import MAX_TRACE_FILES, MAX_TRACE_POINTS

TRACE_FORMATS = ("sabre", "mahimahi", "pensieve", "csv")
TRACE_SUFFIXES = (".json", ".csv", ".log", ".txt", ".up", ".down")
"""Files a trace folder's batch reads (the format of .log, .txt, .up and .down is sniffed)."""
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

    def mean_kbps(self) -> float:
        """Time-weighted mean rate over one period (the last rate where the trace does not loop)."""
        if not math.isfinite(self.period):
            return self.kbps[-1]
        ends = [*self.times[1:], self.period]
        return sum(k * (e - s) for s, e, k in zip(self.times, ends, self.kbps, strict=True)) / self.period

    def scaled(self, factor: float) -> Trace:
        """The same trace with every rate times `factor`."""
        return Trace(list(self.times), [k * factor for k in self.kbps], self.period, self.source)

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


def trace_files(folder: Path, every_file: bool = False) -> list[Path]:
    """A trace folder's files in name order: those with a trace suffix (TRACE_SUFFIXES), or with `every_file` every
    non-hidden file (recorded sets such as Pensieve's name their traces without a suffix, or with a host's)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise StgsError(f"{folder}: not a folder of traces")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                   and (every_file or p.suffix in TRACE_SUFFIXES))
    if not files:
        kinds = "" if every_file else f" ({', '.join(TRACE_SUFFIXES)})"
        raise StgsError(f"{folder}: no trace files{kinds}; formats {', '.join(TRACE_FORMATS)}")
    if len(files) > MAX_TRACE_FILES:
        raise StgsError(f"{folder}: more than {MAX_TRACE_FILES} trace files")
    return files


def load_trace_folder(folder: Path) -> list[Trace]:
    """Every file of a folder (a recorded trace set: Mahimahi, Pensieve, Sabre JSON or CSV files, the format sniffed
    per file; hidden files are skipped), in name order."""
    return [load_trace(p) for p in trace_files(folder, every_file=True)]


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
