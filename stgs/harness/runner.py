"""`stgs sim`: run a scenario with one or both engines, over a folder of traces, or as a load test."""

from __future__ import annotations

import asyncio
import dataclasses
import statistics
import time
from pathlib import Path

import numpy as np

from stgs.client import PlayConfig, play
from stgs.harness.emulate import emulate, scene_url
from stgs.harness.ladder import load_ladder
from stgs.harness.report import (
    metrics,
    plot_cdf,
    plot_timeline,
    row_groups,
    summary_table,
    timeline,
    write_json,
    write_timeline,
)
from stgs.harness.scenario import Scenario
from stgs.harness.sim import simulate
from stgs.harness.trace import load_trace, trace_files
from stgs.tree import MANIFEST

ENGINES = ("sim", "emulate")


def rules(sc: Scenario) -> list[str]:
    return sc.abr if sc.qp is None else sc.abr[:1]


def run_once(sc: Scenario, engine: str, rule: str, ladder, decode: bool = False, speed: float = 1.0) -> dict:
    if engine == "sim":
        return simulate(ladder, sc, rule)
    return emulate(sc, rule, decode, speed)


def run_scenario(sc: Scenario, engines: list[str], out: Path, decode: bool = False, speed: float = 1.0) -> list[dict]:
    """Every (tree, engine, rule) playback of one scenario (its `scene` and each tree it compares with); writes
    logs, timelines, plots and one summary under out."""
    results = []
    for variant in sc.variants():
        ladder = load_ladder(variant.scene, variant.codec)
        for rule in rules(variant):
            for engine in engines:
                start = time.perf_counter()
                log = run_once(variant, engine, rule, ladder, decode, speed)
                seconds = time.perf_counter() - start
                m = metrics(log, ladder, variant.effects) | {"scenario": variant.name, "wall_s": seconds,
                                                             "scene": variant.label,
                                                             "format": 1 if ladder.pres.static is None else 2}
                stem = f"{variant.name}-{engine}-{rule}"
                write_json(out / f"{stem}.log.json", log)
                write_timeline(out / f"{stem}.timeline.csv", timeline(log, variant.effects))
                plot_timeline(out / f"{stem}.png", log, variant.effects.bandwidth,
                              f"{variant.name}: {engine}, {rule}")
                results.append(m)
    write_json(out / f"{sc.name}.summary.json", results)
    (out / f"{sc.name}.summary.md").write_text(summary_table(results) + "\n")
    return results


def run_batch(sc: Scenario, traces: Path, engines: list[str], out: Path, speed: float = 1.0) -> list[dict]:
    """The scenario once per trace file in `traces` (its bandwidth replaced by the trace), per rule and engine."""
    files = trace_files(traces)
    rows = []
    for tree in sc.variants():
        ladder = load_ladder(tree.scene, tree.codec)
        for f in files:
            trace = load_trace(f)
            variant = dataclasses.replace(tree, name=f"{tree.name}-{f.stem}",
                                          effects=dataclasses.replace(tree.effects, bandwidth=trace))
            for rule in rules(variant):
                for engine in engines:
                    log = run_once(variant, engine, rule, ladder, speed=speed)
                    rows.append(metrics(log, ladder, variant.effects) | {
                        "scenario": variant.name, "trace": f.name, "scene": tree.label,
                        "format": 1 if ladder.pres.static is None else 2})
    write_json(out / f"{sc.name}.batch.json", rows)
    (out / f"{sc.name}.batch.md").write_text(summary_table(rows) + "\n")
    qoe = {label: [r["qoe_nominal"] for r in group] for label, group in row_groups(rows).items()}
    plot_cdf(out / f"{sc.name}.qoe_cdf.png", qoe, "QoE per GOP (Pensieve linear, nominal bit rates)")
    return rows


async def _load(sc: Scenario, counts: list[int]) -> list[dict]:
    ladder = load_ladder(sc.scene, sc.codec)
    rows = []
    async with scene_url(sc.scene) as base:
        for n in counts:
            cfg = PlayConfig(base + MANIFEST, abr=rules(sc)[0], qp=sc.qp, codec=sc.codec, buffer_s=sc.buffer_s,
                             start_s=sc.start_s, duration_s=sc.duration_s, realtime=True, decode=False)
            start = time.perf_counter()
            logs = await asyncio.gather(*(play(dataclasses.replace(cfg)) for _ in range(n)))
            wall = time.perf_counter() - start
            served = sum(log["bytes"] for log in logs)
            downloads = sorted(g["download_s"] for log in logs for g in log["gops"])
            ttfb = sorted(g["ttfb_s"] for log in logs for g in log["gops"])
            qoe = [metrics(log, ladder, sc.effects)["qoe_nominal"] for log in logs]
            rows.append({"clients": n, "wall_s": wall, "server_mb_s": served / 1e6 / wall,
                         "gop_download_p50_s": _pct(downloads, 50), "gop_download_p99_s": _pct(downloads, 99),
                         "ttfb_p50_ms": _pct(ttfb, 50) * 1e3, "ttfb_p99_ms": _pct(ttfb, 99) * 1e3,
                         "mean_qoe": statistics.mean(qoe), "stalls": sum(log["stalls"]["count"] for log in logs)})
    return rows


def _pct(values: list[float], p: float) -> float:
    return float(np.percentile(values, p)) if values else float("nan")


def run_load(sc: Scenario, counts: list[int], out: Path) -> list[dict]:
    """N real players (no decoding) against one real server on loopback, for each N."""
    rows = asyncio.run(_load(sc, counts))
    write_json(out / f"{sc.name}.load.json", rows)
    lines = ["| clients | server MB/s | GOP download p50 / p99 (s) | TTFB p50 / p99 (ms) | mean QoE | stalls |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['clients']} | {r['server_mb_s']:.2f} | {r['gop_download_p50_s']:.3f} / "
              f"{r['gop_download_p99_s']:.3f} | {r['ttfb_p50_ms']:.1f} / {r['ttfb_p99_ms']:.1f} | "
              f"{r['mean_qoe']:.3f} | {r['stalls']} |" for r in rows]
    (out / f"{sc.name}.load.md").write_text("\n".join(lines) + "\n")
    return rows
