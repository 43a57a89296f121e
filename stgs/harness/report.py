"""QoE reports of playback logs (simulated or emulated alike), timelines, plots and batch summaries.

Three QoEs, each Pensieve's linear form (Mao et al., SIGCOMM 2017) per GOP,
    QoE = (Σ_k q_k − μ · rebuffer_s − Σ_k |q_{k+1} − q_k|) / GOPs,
named apart by what q is:
- `qoe_nominal`, as published (Pensieve, and simulators such as Sabre): q = the chosen rung's nominal bit rate
  in Mbit/s, μ = 4.3. A rung's nominal rate is its mean over the scene's GOPs (keyframe + features), one number
  per rung, so a steady rung pays no switch penalty, as with an encoder's nominal ladder.
- `qoe_size`, ours: q = the bit rate of the GOP's download (keyframe + features over the GOP's duration), μ = 4.3;
  a steady rung pays for its GOPs' size variation.
- `qoe_psnr`, what the viewer sees: q = the GOP's rendered PSNR in dB (stats.json), 10 dB per second of stall
  (`REBUFFER_PENALTY_DB`, the look-ahead rule's default weight).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
from pathlib import Path

from stgs.client.abr import AbrSettings
from stgs.fsio import atomic_write_bytes, save_figure
from stgs.harness.ladder import Ladder
from stgs.harness.scenario import Effects
from stgs.harness.trace import Trace

REBUFFER_PENALTY = 4.3
"""μ of the linear QoE (Pensieve's value for bit rates in Mbit/s)."""
REBUFFER_PENALTY_DB = AbrSettings().mpc_rebuffer_psnr
"""μ of the quality QoE (dB per second of stall)."""


def linear_qoe(values: list[float], stall_s: float, mu: float) -> float:
    """Σ q − μ · stall − Σ |Δq|, per GOP."""
    if not values:
        return -math.inf
    return (sum(values) - mu * stall_s - sum(abs(b - a) for a, b in itertools.pairwise(values))) / len(values)


def nominal_mbps(ladder: Ladder) -> dict[str, float]:
    """Representation id -> its nominal bit rate (Mbit/s): keyframe + features, mean over the scene's GOPs."""
    T = ladder.pres.segment_seconds
    keyframe = sum(ladder.keyframe_bytes) / len(ladder.keyframe_bytes)
    return {rep: (keyframe + sum(sizes) / len(sizes)) * 8 / T / 1e6 for rep, sizes in ladder.media_bytes.items()}


def metrics(log: dict, ladder: Ladder, effects: Effects) -> dict:
    """One playback's report."""
    gops = [g for g in log["gops"] if g["rep"]]
    T = log["segment_s"]
    rates = [(g["keyframe_bytes"] + g["feature_bytes"]) * 8 / T / 1e6 for g in gops]
    nominal = nominal_mbps(ladder)
    quality = [ladder.psnr[g["rep"]][g["index"]] for g in gops]
    stall = log["stalls"]["total_s"]
    played = len(gops) * T
    return {
        "engine": log.get("engine", "play"), "abr": log["abr"], "active_effects": effects.describe(),
        "startup_delay_s": log["startup_delay_s"], "stall_count": log["stalls"]["count"], "stall_s": stall,
        "rebuffer_ratio": stall / (played + stall) if played + stall else 0.0,
        "mean_bitrate_kbps": sum(rates) / len(rates) * 1e3 if rates else 0.0,
        "mean_quality_db": (sum(quality) / len(quality)) if quality and None not in quality else None,
        "switches": log["switches"], "wasted_bytes": log["wasted_bytes"],
        "qoe_nominal": linear_qoe([nominal[g["rep"]] for g in gops], stall, REBUFFER_PENALTY),
        "qoe_size": linear_qoe(rates, stall, REBUFFER_PENALTY), "qps": [g["qp"] for g in gops],
        "static_bytes": log.get("static_bytes", 0), "kb_per_frame": log.get("kb_per_frame"),
        "qoe_psnr": linear_qoe(quality, stall, REBUFFER_PENALTY_DB) if None not in quality else None,
        "error": log.get("error"),
    }


TIMELINE_COLUMNS = ("index", "rep", "qp", "rule", "buffer_s", "estimate_kbps", "keyframe_bytes", "feature_bytes",
                    "init_bytes", "fetch_start_s", "fetch_end_s", "play_start_s", "stall_s", "abandoned_bytes")


def timeline(log: dict, effects: Effects) -> list[dict]:
    """Per-GOP rows, with the latency and loss the network applied (0 where the effect is not active)."""
    rows = []
    for g in log["gops"]:
        row = {c: g.get(c) for c in TIMELINE_COLUMNS}
        lat = g.get("latency_ms") or []
        row["latency_ms"] = sum(lat) / len(lat) if lat else 0.0
        row["loss"] = effects.loss or 0.0
        rows.append(row)
    return rows


def write_timeline(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else list(TIMELINE_COLUMNS))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def write_json(path: Path, doc: object) -> None:
    atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_timeline(path: Path, log: dict, bandwidth: Trace | None, title: str) -> None:
    """Throughput available vs chosen bit rate vs buffer level over time."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4))
    gops = [g for g in log["gops"] if g["rep"]]
    end = max([g["fetch_end_s"] for g in gops] + [g["play_start_s"] or 0 for g in gops]) + log["segment_s"]
    if bandwidth is not None:
        ts = [i * end / 400 for i in range(401)]
        ax.step(ts, [bandwidth.segment(t)[0] for t in ts], where="post", label="bandwidth (kbit/s)", color="0.6")
    T = log["segment_s"]
    ax.step([g["fetch_start_s"] for g in gops], [(g["keyframe_bytes"] + g["feature_bytes"]) * 8 / T / 1e3
                                                   for g in gops], where="post", label="chosen bit rate (kbit/s)")
    ax.set_xlabel("seconds")
    ax.set_ylabel("kbit/s")
    ax2 = ax.twinx()
    ax2.plot([g["fetch_start_s"] for g in gops], [g["buffer_s"] for g in gops], "o-", color="tab:green",
             label="buffer at decision (s)")
    ax2.set_ylabel("buffer (s)")
    lines = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    ax.legend(lines, [h.get_label() for h in lines], loc="upper right", fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)


def plot_cdf(path: Path, values: dict[str, list[float]], xlabel: str) -> None:
    """CDF per ABR rule of one metric across traces."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, vals in values.items():
        xs = sorted(vals)
        ax.step(xs, [(i + 1) / len(xs) for i in range(len(xs))], where="post", label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("fraction of traces")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def row_groups(rows: list[dict]) -> dict[str, list[dict]]:
    """Playbacks grouped by ABR rule and engine, and by tree where a scenario compares several."""
    groups: dict[str, list[dict]] = {}
    several = len({r.get("scene") for r in rows}) > 1
    for r in rows:
        tree = f"{r['scene']} (format {r['format']}): " if several else ""
        groups.setdefault(f"{tree}{r['abr']} ({r['engine']})", []).append(r)
    return groups


def summary_table(rows: list[dict]) -> str:
    """Markdown: mean of each metric per group of `row_groups` over the playbacks in `rows`."""
    by_rule = row_groups(rows)
    lines = ["| ABR (engine) | playbacks | QoE (nominal) | QoE (sizes) | QoE (PSNR) | mean bit rate (kbit/s) | "
             "mean quality (dB) | stalls | stall s | rebuffer % | switches | startup s | kB/frame |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for rule, rs in by_rule.items():
        def mean(key: str, rs=rs) -> float:
            vals = [r[key] for r in rs if r[key] is not None]
            return sum(vals) / len(vals) if vals else math.nan
        lines.append(f"| {rule} | {len(rs)} | {mean('qoe_nominal'):.3f} | {mean('qoe_size'):.3f} | "
                     f"{mean('qoe_psnr'):.2f} | {mean('mean_bitrate_kbps'):.0f} | "
                     f"{mean('mean_quality_db'):.2f} | {mean('stall_count'):.2f} | {mean('stall_s'):.2f} | "
                     f"{100 * mean('rebuffer_ratio'):.1f} | {mean('switches'):.2f} | {mean('startup_delay_s'):.2f} | "
                     f"{mean('kb_per_frame'):.2f} |")
    return "\n".join(lines)


def sabre_manifest(ladder: Ladder) -> dict:
    """The scene's ladder as Sabre's manifest JSON. Each size is a whole GOP (keyframe + features), so Sabre
    budgets the fixed keyframe as our player does; segment 0 also carries its rung's init segment (our player
    fetches it before the first GOP's features). One request per segment matches our player after its first GOP
    (keyframe and features are asked for together). A layered scene's static layer, fetched once before the
    first GOP, is budgeted in segment 0 too (its bits are also given alone). What Sabre cannot express is listed
    under `streamstgs`: the init segment a later switch to a new rung costs, and the first GOP's requests."""
    pres = ladder.pres
    reps = [r.rep_id for r in pres.ladder]
    sizes = [[(ladder.keyframe_bytes[k] + ladder.media_bytes[r][k]) * 8 for r in reps] for k in range(pres.num_gops)]
    T = pres.segment_seconds
    bitrates = [sum(s[i] for s in sizes) / len(sizes) / T / 1e3 for i in range(len(reps))]
    init_bits = [ladder.init_bytes[r] * 8 for r in reps]
    static_bits = ladder.static_bytes * 8
    if sizes:
        sizes[0] = [s + i + static_bits for s, i in zip(sizes[0], init_bits, strict=True)]
    first = 3 + (1 if static_bits else 0)
    not_expressible = ["the init segment of a rung first used after segment 0 (its bits are in "
                       "init_segment_bits, not in that segment)",
                       f"the first GOP's requests are {first} round trips ({'static layer, ' if static_bits else ''}"
                       "keyframe, init, media)"]
    if static_bits:
        not_expressible.append("the static layer is fetched once per playback whatever the start segment; Sabre "
                               "counts it in segment 0 only (a playback starting later pays it in its first)")
    return {"segment_duration_ms": round(T * 1e3, 3), "bitrates_kbps": bitrates, "segment_sizes_bits": sizes,
            "streamstgs": {
                "init_segment_bits": init_bits, "static_layer_bits": static_bits,
                "static_layer_budget": "segment 0" if static_bits else "none (format 1)",
                "requests_per_segment": 1, "first_segment_requests": first,
                "not_expressible": not_expressible}}
