"""ABR rules over trace sets (`stgs bench abr`): QoE, rebuffering, bit rate, PSNR, switches, start-up; the ladder floor.

The scene: a packaged scene (`--dash`, default: the `demo` synthetic scene
packed at QPs 16-40), its GOPs repeated to 180 s as one long presentation
(sizes and per-rung rendered PSNR from the packed files and stats.json).
Trace sets: recorded ones (`--traces DIR,...`: one set per folder of
Mahimahi, Pensieve or Sabre-JSON files), or else generated here (written in
the public formats and read back through `load_trace`, so the readers are
exercised too): each trace a per-second log-rate AR(1) process with fades,
bursty, heavy-tailed sets with long outages among them. Each set is scaled by
one constant so that its median trace's mean equals the top rung (keyframe +
top features). Every rule runs on every trace at 6 s and 25 s of buffer in
the discrete-event simulator; each cell reports every rule's difference from
the cell's best classic rule, paired by trace, with a 95 % confidence interval.
"""

from __future__ import annotations

import dataclasses
import math
import platform
import random
import re
import statistics
import tempfile
import time
from pathlib import Path

import scipy.stats

from stgs.client.abr import AbrSettings
from stgs.client.manifest import Presentation
from stgs.errors import StgsError
from stgs.harness.ladder import Ladder, load_ladder
from stgs.harness.report import metrics
from stgs.harness.scenario import scenario_from_dict
from stgs.harness.sim import simulate
from stgs.harness.trace import MAHIMAHI_PACKET_BITS, Trace, load_trace, load_trace_folder
from stgs.packager import PackConfig, pack
from stgs.synth import PRESETS, synthesize
from stgs.tree import MANIFEST

SECONDS = 180
TRACES_PER_SET = 16
TRACE_S = 320
BUFFERS = (6.0, 25.0)
FLOOR_QPS = (16, 20, 24, 28, 32, 36, 40)


@dataclasses.dataclass(frozen=True)
class TraceSet:
    name: str
    fmt: str
    """The public format the traces are written in (mahimahi or pensieve)."""
    phi: float
    """AR(1) coefficient of the log rate per second."""
    sigma: float
    """Innovation of the log rate per second."""
    fade_p: float
    """Chance per second that a fade starts."""
    fade_depth: tuple[float, float]
    """A fade multiplies the rate by a factor drawn from this range ..."""
    latency_ms: float
    fade_s: tuple[int, int] = (1, 4)
    """... for a whole number of seconds drawn from this range."""


SETS = (
    TraceSet("cellular (LTE-like)", "mahimahi", 0.92, 0.30, 0.03, (0.05, 0.3), 60.0),
    TraceSet("3G (HSDPA-like)", "pensieve", 0.85, 0.50, 0.05, (0.0, 0.2), 100.0),
    TraceSet("broadband (FCC-like)", "pensieve", 0.97, 0.10, 0.005, (0.3, 0.6), 20.0),
    TraceSet("bursty (Puffer-like)", "mahimahi", 0.80, 0.80, 0.02, (0.0, 0.05), 40.0, (3, 12)),
    TraceSet("broadband with dips", "pensieve", 0.98, 0.05, 0.02, (0.1, 0.3), 15.0, (1, 2)),
)
"""Generated trace sets. The last two are where rules lose most: heavy-tailed throughput (a log-normal of σ 0.8
per second: a second at 5x the median is as common as one at a fifth) with outages of 3-12 s, and steady
broadband with frequent brief dips."""
CLASSIC = ("throughput", "bola", "bola-e", "dynamic")
"""The classic rules the targets are set against (the best of them per cell)."""
RULES = {"throughput": ("throughput", None), "bola": ("bola", None), "bola-e": ("bola-e", None),
         "dynamic": ("dynamic", None), "mpc": ("mpc", AbrSettings()),
         "mpc (bit-rate utility)": ("mpc", AbrSettings(mpc_utility="bitrate")),
         "RobustMPC (PSNR, harmonic)": ("mpc", AbrSettings(mpc_predictor="harmonic", mpc_buffer_constraint=False,
                                                           mpc_utility="psnr"))}
"""Every rule at its defaults (mpc: the quality utility); mpc also with the bit-rate utility (the default until the
auto ladder was measured), and as RobustMPC was before its predictor and buffer constraint (the default until they
were measured)."""


def generate(ts: TraceSet, seed: int) -> list[float]:
    """Relative rate per second (mean-1 log-normal AR(1) with fades)."""
    rng = random.Random(seed)
    x, fade, factor, out = 0.0, 0, 1.0, []
    for _ in range(TRACE_S):
        x = ts.phi * x + ts.sigma * rng.gauss(0, 1)
        if fade == 0 and rng.random() < ts.fade_p:
            fade, factor = rng.randint(*ts.fade_s), rng.uniform(*ts.fade_depth)
        rate = math.exp(x) * (factor if fade else 1.0)
        fade = max(0, fade - 1)
        out.append(rate)
    return out


def write(rates_kbps: list[float], fmt: str, path: Path) -> None:
    """Pensieve: seconds, Mbit/s per line. Mahimahi: one line per 1500-byte delivery opportunity (ms)."""
    if fmt == "pensieve":
        path.write_text("".join(f"{t} {r / 1e3:.6f}\n" for t, r in enumerate(rates_kbps)))
        return
    lines, carry = [], 0.0
    for second, kbps in enumerate(rates_kbps):
        for ms in range(1000):
            carry += kbps  # bits per ms
            while carry >= MAHIMAHI_PACKET_BITS:
                carry -= MAHIMAHI_PACKET_BITS
                lines.append(f"{second * 1000 + ms}\n")
    lines.append(f"{len(rates_kbps) * 1000}\n")
    path.write_text("".join(lines))


def trace_set(ts: TraceSet, top_kbps: float, folder: Path) -> list[Trace]:
    relative = [generate(ts, seed) for seed in range(TRACES_PER_SET)]
    scale = top_kbps / statistics.median(statistics.mean(r) for r in relative)
    traces = []
    for i, rel in enumerate(relative):
        slug = re.sub(r"\W+", "-", ts.name).strip("-").lower()
        path = folder / f"{slug}-{i:02d}.{'down' if ts.fmt == 'mahimahi' else 'log'}"
        write([r * scale for r in rel], ts.fmt, path)
        traces.append(load_trace(path))
    return traces


def long_ladder(ladder: Ladder, mpd: str, seconds: int, qps: tuple[int, ...] | None = None) -> Ladder:
    """The packed scene (`mpd`: its manifest's text) with its GOPs repeated to `seconds`, optionally only the
    rungs of `qps`."""
    pres = ladder.pres
    gops = round(seconds / pres.segment_seconds)
    keep = [r for r in pres.ladder if qps is None or r.qp in qps]
    mpd = re.sub(r'mediaPresentationDuration="[^"]*"',
                 f'mediaPresentationDuration="PT{gops * pres.segment_seconds:g}S"', mpd)
    for r in pres.ladder:
        if r not in keep:
            start = mpd.index(f'<Representation id="{r.rep_id}"')
            mpd = mpd[:start] + mpd[mpd.index("/>", start) + 2:]
    long = Presentation.parse(mpd.encode(), ladder.url)
    n = pres.num_gops

    def rep(values: list) -> list:
        return [values[k % n] for k in range(gops)]

    ids = [r.rep_id for r in keep]
    return Ladder(long, rep(ladder.keyframe_bytes), {r: rep(ladder.media_bytes[r]) for r in ids},
                  {r: ladder.init_bytes[r] for r in ids}, {r: rep(ladder.psnr[r]) for r in ids}, ladder.stats,
                  ladder.static_bytes, {r: rep(sizes) for r, sizes in ladder.lossy_keyframe_bytes.items()})


def playbacks(ladder: Ladder, traces: list[Trace], latency_ms: float, buffer_s: float, rule: str,
              settings: AbrSettings | None) -> list[dict]:
    """One simulated playback per trace: its harness metrics, in trace order."""
    rows = []
    for trace in traces:
        sc = scenario_from_dict({"scene": "unused", "buffer_s": buffer_s, "effects": {"latency_ms": latency_ms}},
                                trace.source or "trace", Path("."))
        sc = dataclasses.replace(sc, effects=dataclasses.replace(sc.effects, bandwidth=trace))
        rows.append(metrics(simulate(ladder, sc, rule, settings), ladder, sc.effects))
    return rows


def summary(rows: list[dict], ladder: Ladder) -> dict:
    """Means over playbacks; rebuffering pooled (all stall time over all played + stall time)."""
    stall = sum(r["stall_s"] for r in rows)
    played = sum(len(r["qps"]) for r in rows) * ladder.pres.segment_seconds
    return {"qoe_nominal": statistics.mean(r["qoe_nominal"] for r in rows),
            "qoe_size": statistics.mean(r["qoe_size"] for r in rows),
            "qoe_psnr": statistics.mean(r["qoe_psnr"] for r in rows),
            "rebuffer_pct": 100 * stall / (played + stall), "bitrate": statistics.mean(r["mean_bitrate_kbps"]
                                                                                      for r in rows),
            "psnr": statistics.mean(r["mean_quality_db"] for r in rows),
            "switches": statistics.mean(r["switches"] for r in rows),
            "startup": statistics.mean(r["startup_delay_s"] for r in rows)}


def run(ladder: Ladder, traces: list[Trace], ts: TraceSet, buffer_s: float, rule: str,
        settings: AbrSettings | None) -> dict:
    return summary(playbacks(ladder, traces, ts.latency_ms, buffer_s, rule, settings), ladder)


def paired_ci(a: list[float], b: list[float], confidence: float = 0.95) -> tuple[float, float]:
    """Mean of a − b paired by trace and the half-width of its Student-t confidence interval (inf below 2 pairs)."""
    diffs = [x - y for x, y in zip(a, b, strict=True)]
    mean = statistics.mean(diffs)
    if len(diffs) < 2:
        return mean, math.inf
    half = scipy.stats.t.ppf(0.5 + confidence / 2, len(diffs) - 1) * statistics.stdev(diffs) / math.sqrt(len(diffs))
    return mean, float(half)


def packed_scene(tmp: Path) -> Path:
    print(f"synthesising the demo scene and packing it at QPs {', '.join(map(str, FLOOR_QPS))} ...", flush=True)
    synthesize(PRESETS["demo"], tmp / "model", progress=False)
    pack(tmp / "model", tmp / "dash", PackConfig(ladder="fixed", qps=FLOOR_QPS), progress=False)
    return tmp / "dash"


def rd_table(ladder: Ladder) -> None:
    T, G = ladder.pres.segment_seconds, ladder.pres.shape.gop_size
    print("| QP | features kbit/s | keyframe + features kbit/s | KB/frame | rendered PSNR dB |")
    print("|---|---|---|---|---|")
    for i, r in reversed(list(enumerate(ladder.pres.ladder))):
        kf = statistics.mean(ladder.rung_keyframe_bytes(i))  # the keyframes this rung plays with
        media = statistics.mean(ladder.media_bytes[r.rep_id])
        print(f"| {r.qp} | {media * 8 / T / 1e3:.0f} | {(kf + media) * 8 / T / 1e3:.0f} | {(kf + media) / G / 1e3:.1f} "
              f"| {statistics.mean(ladder.psnr[r.rep_id]):.2f} |")


@dataclasses.dataclass
class CellSet:
    """A trace set as the bench runs it: its name, traces (scaled) and round trip."""

    name: str
    traces: list[Trace]
    latency_ms: float
    origin: str
    """How the traces came (generated and written in a format, or read from a folder)."""


def recorded_sets(folders: list[Path], latency_ms: float, top_kbps: float | None) -> list[CellSet]:
    """Each folder one recorded set (load_trace_folder); `top_kbps` not None: each set scaled by one constant so
    that its median trace's mean equals it."""
    sets = []
    for folder in folders:
        traces = load_trace_folder(folder)
        origin = f"{len(traces)} recorded traces from {folder}"
        if top_kbps is not None:
            median = statistics.median(t.mean_kbps() for t in traces)
            if median <= 0:
                raise StgsError(f"{folder}: the median trace delivers nothing; it cannot be scaled")
            traces = [t.scaled(top_kbps / median) for t in traces]
            origin += f", scaled x{top_kbps / median:.3g}"
        sets.append(CellSet(folder.name, traces, latency_ms, origin))
    return sets


def cell_table(ladder: Ladder, cs: CellSet, buffer_s: float) -> None:
    """Every rule over one set at one buffer, and each rule's difference from the best classic rule of the cell,
    paired by trace, with its 95 % confidence interval."""
    results, rates = {}, {}
    for name, (rule, settings) in RULES.items():
        start = time.perf_counter()
        results[name] = playbacks(ladder, cs.traces, cs.latency_ms, buffer_s, rule, settings)
        rates[name] = len(cs.traces) / (time.perf_counter() - start)
    means = {name: summary(rows, ladder) for name, rows in results.items()}
    ref = max(CLASSIC, key=lambda name: means[name]["qoe_nominal"])
    print(f"| rule | QoE (nominal) | QoE (sizes) | QoE (PSNR) | rebuffer % | mean kbit/s | mean PSNR dB | switches "
          f"| start-up s | ΔQoE (nominal) vs {ref}, 95 % CI | Δstall s vs {ref}, 95 % CI | playbacks/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, m in means.items():
        dq = paired_ci([r["qoe_nominal"] for r in results[name]], [r["qoe_nominal"] for r in results[ref]])
        ds = paired_ci([r["stall_s"] for r in results[name]], [r["stall_s"] for r in results[ref]])
        print(f"| {name} | {m['qoe_nominal']:.3f} | {m['qoe_size']:.3f} | {m['qoe_psnr']:.2f} | "
              f"{m['rebuffer_pct']:.2f} | {m['bitrate']:.0f} | {m['psnr']:.2f} | {m['switches']:.1f} | "
              f"{m['startup']:.2f} | {dq[0]:+.3f} ± {dq[1]:.3f} | {ds[0]:+.2f} ± {ds[1]:.2f} | {rates[name]:.1f} |",
              flush=True)


LADDER_RULES = ("mpc", "mpc (bit-rate utility)")
"""The rules `--against` plays on both ladders: the default (quality utility) and its bit-rate utility."""


def compare_ladders(dash: Path, against: Path) -> int:
    """Two packagings of one model (e.g. its fixed ladder and its auto ladder) on the same generated traces, scaled
    to `dash`'s top rung: per trace set, buffer and rule of LADDER_RULES, the mean rendered PSNR, bit rate and
    rebuffering of each, and their pooled means over every cell."""
    with tempfile.TemporaryDirectory(prefix="stgs-bench-abr-") as tmp:
        ladders = {}
        for tree in (dash, against):
            ladders[tree] = long_ladder(load_ladder(str(tree)), (tree / MANIFEST).read_text(), SECONDS)
        first = ladders[dash]
        top_kbps = first.rung_kbps(-1)
        print(f"\nMachine: {platform.machine()} {platform.processor() or ''}; A = {dash}, B = {against}, each repeated "
              f"to {SECONDS} s; traces scaled to A's top rung, {top_kbps:.0f} kbit/s\n")
        for tree, ladder in ladders.items():
            print(f"{tree}: rungs {', '.join(r.rep_id for r in ladder.pres.ladder)}")
        print("\n| trace set | buffer s | rule | PSNR A dB | PSNR B dB | ΔPSNR dB | kbit/s A | kbit/s B | B/A bytes "
              "| rebuffer % A | rebuffer % B |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        pooled: dict[str, list[tuple[dict, dict]]] = {rule: [] for rule in LADDER_RULES}
        for ts in SETS:
            traces = trace_set(ts, top_kbps, Path(tmp))
            for buffer_s in BUFFERS:
                for rule in LADDER_RULES:
                    a, b = (run(ladders[t], traces, ts, buffer_s, *RULES[rule]) for t in (dash, against))
                    pooled[rule].append((a, b))
                    print(f"| {ts.name} | {buffer_s:g} | {rule} | {a['psnr']:.2f} | {b['psnr']:.2f} "
                          f"| {b['psnr'] - a['psnr']:+.2f} | {a['bitrate']:.0f} | {b['bitrate']:.0f} "
                          f"| {b['bitrate'] / a['bitrate']:.2f} | {a['rebuffer_pct']:.2f} | {b['rebuffer_pct']:.2f} |",
                          flush=True)
        print("\n| ladder | rule | cells | mean PSNR dB | mean kbit/s | rebuffer % | QoE (PSNR) |")
        print("|---|---|---|---|---|---|---|")
        for side, tree in enumerate((dash, against)):
            for rule, cells in pooled.items():
                def mean(key: str, cells: list = cells, side: int = side) -> float:
                    return statistics.mean(c[side][key] for c in cells)
                print(f"| {'AB'[side]}: {tree.name} | {rule} | {len(cells)} | {mean('psnr'):.2f} "
                      f"| {mean('bitrate'):.0f} | {mean('rebuffer_pct'):.2f} | {mean('qoe_psnr'):.2f} |")
    return 0


def main(dash: Path | None, trace_dirs: list[Path] | None = None, latency_ms: float = 40.0,
         scale: bool = True) -> int:
    """`trace_dirs`: recorded trace sets, one per folder, instead of the generated ones (then only the full ladder is
    run: the ladder without its floor rungs is the generated sets' comparison)."""
    with tempfile.TemporaryDirectory(prefix="stgs-bench-abr-") as tmp:
        dash = dash or packed_scene(Path(tmp))
        base = load_ladder(str(dash))
        qps = tuple(r.qp for r in base.pres.ladder)
        mpd = (dash / MANIFEST).read_text()
        ladders = {f"QP {min(qps)}-{max(qps)}": long_ladder(base, mpd, SECONDS)}
        if max(qps) > 32 and not trace_dirs:
            ladders[f"QP {min(qps)}-32 (no floor rungs)"] = long_ladder(base, mpd, SECONDS,
                                                                        tuple(q for q in qps if q <= 32))
        print(f"\nMachine: {platform.machine()} {platform.processor() or ''}; scene {dash} repeated to {SECONDS} s\n")
        rd_table(ladders[next(iter(ladders))])
        for lname, ladder in ladders.items():
            top_kbps = ladder.rung_kbps(-1)
            if trace_dirs:
                sets = recorded_sets(trace_dirs, latency_ms, top_kbps if scale else None)
            else:
                sets = [CellSet(ts.name, trace_set(ts, top_kbps, Path(tmp)), ts.latency_ms,
                                f"{TRACES_PER_SET} traces written as {ts.fmt}") for ts in SETS]
            for cs in sets:
                for buffer_s in BUFFERS:
                    print(f"\n**{cs.name}, ladder {lname}, buffer {buffer_s:g} s** ({cs.origin}, "
                          f"{cs.latency_ms:g} ms round trips, top rung {top_kbps:.0f} kbit/s)\n")
                    cell_table(ladder, cs, buffer_s)
    return 0
