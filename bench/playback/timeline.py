"""Per-frame timeline of a playback log: where each frame's time goes, renderer and feature decoder side by side.

    python -m bench.playback.timeline playback.json out.png [--from 2 --seconds 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

COLOURS = {"wait": "#bbbbbb", "deform": "#4c72b0", "splat": "#dd8452", "decode": "#55a868",
           "dequantise": "#8172b2"}


def spans(log: dict) -> dict[str, list[tuple[float, float]]]:
    """(start, duration) in seconds per kind of work, over the whole playback."""
    out: dict[str, list[tuple[float, float]]] = {k: [] for k in COLOURS}
    for g in log["gops"]:
        for at, wait, deform, splat in zip(g["render_at_s"], g["wait_ms"], g["deform_ms"], g["splat_ms"],
                                           strict=True):
            out["wait"].append((at, wait / 1e3))
            out["deform"].append((at + wait / 1e3, deform / 1e3))
            out["splat"].append((at + (wait + deform) / 1e3, splat / 1e3))
        for at, decode, deq in zip(g["decode_at_s"], g["decode_ms"], g["dequantise_ms"], strict=True):
            out["decode"].append((at, decode / 1e3))
            out["dequantise"].append((at + decode / 1e3, deq / 1e3))
    return out


def plot_timeline(log: dict, path: Path, start: float | None = None, seconds: float = 2.0, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    work = spans(log)
    renders = sorted(t for t, _ in work["deform"])
    if start is None:  # a window in the middle of the playback
        start = renders[len(renders) // 2] if renders else 0.0
    end = start + seconds
    fig, ax = plt.subplots(figsize=(12, 2.6))
    rows = {"renderer (all kernel threads)": ("wait", "deform", "splat"), "feature decoder": ("decode", "dequantise")}
    for y, kinds in enumerate(rows.values()):
        for kind in kinds:
            bars = [(t, d) for t, d in work[kind] if t + d >= start and t <= end]
            ax.broken_barh(bars, (y - 0.35, 0.7), color=COLOURS[kind], label=kind)
    fps_ticks = [t for g in log["gops"] if g["play_start_s"] is not None
                 for t in (g["play_start_s"] + i / log["fps"] for i in range(g["presented"]))
                 if start <= t <= end]
    for t in fps_ticks:
        ax.axvline(t, color="black", lw=0.3, alpha=0.4)
    ax.set_yticks(range(len(rows)), list(rows))
    ax.set_xlim(start, end)
    ax.set_xlabel("seconds since playback began (thin lines: frame due times; white: idle)")
    ax.legend(ncol=5, loc="upper center", bbox_to_anchor=(0.5, 1.32), frameon=False)
    ax.set_title(title, fontsize=9, loc="left", pad=28)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--from", dest="start", type=float)
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    plot_timeline(json.loads(args.log.read_text()), args.out, args.start, args.seconds, args.log.stem)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
