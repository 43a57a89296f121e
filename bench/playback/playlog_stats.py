"""What a playback log says, as the real-time benchmarks tabulate it: per-frame quantiles, the 30-fps verdict,
start-up and seek over repeated runs, and the host's steal share of a run (bench/playback/realtime.py,
bench/playback/knobs.py)."""

from __future__ import annotations

import math
import statistics
from pathlib import Path


def cpu_times() -> tuple[int, int] | None:
    """(steal, total) jiffies of all CPUs since boot from /proc/stat; None where there is none (not Linux)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    values = [int(v) for v in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return (values[7] if len(values) > 7 else 0), sum(values)


def steal_share(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """Share of the CPU time the hypervisor gave to others between two cpu_times() (a busy host: the run's
    timings and drops measure the host, not the player)."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


def quantiles(values: list[float]) -> tuple[float, float]:
    """(median, 95th percentile)."""
    if not values:
        return math.nan, math.nan
    ordered = sorted(values)
    return statistics.median(ordered), ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))]


def frame_stats(log: dict) -> dict[str, tuple[float, float]]:
    gops = log["gops"]

    def every(key: str) -> list[float]:
        return [v for g in gops for v in g[key]]

    frame = [d + q for g in gops for d, q in zip(g["decode_ms"], g["dequantise_ms"], strict=True)]
    return {"decode": quantiles(frame), "wait": quantiles(every("wait_ms")), "deform": quantiles(every("deform_ms")),
            "splat": quantiles(every("splat_ms")), "render": quantiles(every("render_ms"))}


def held_realtime(log: dict) -> bool:
    """The playback held 30 fps for its whole length: no dropped frame, no stall, no error."""
    return log["dropped_frames"] == 0 and log["stalls"]["count"] == 0 and log["error"] is None


def latency_cell(logs: list[dict]) -> str:
    """Time to first frame over repeated runs: the median, and the worst in brackets; a run that never showed
    a frame counts as the worst."""
    times = [log["time_to_first_frame_s"] for log in logs]
    if not times:
        return "–"
    shown = sorted(t for t in times if t is not None)
    worst = "never" if len(shown) < len(times) else f"{shown[-1]:.2f}"
    middle = f"{statistics.median(shown):.2f}" if len(shown) * 2 > len(times) else "never"
    return middle if len(times) == 1 else f"{middle} ({worst})"
