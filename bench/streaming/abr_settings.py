"""The experiments that set the ABR defaults: each setting of a group over bench.streaming.abr's scene and trace sets
(`python -m bench.streaming.abr_settings --group stability|mpc`, prints Markdown for docs/BENCHMARKS.md,
"ABR rules over trace sets").

- `stability`: the hysteresis (AbrSettings.sustained_gops, switch_up_headroom, mpc_switch_margin_s). The scene's GOPs
  alternate in size, the case where deciding on the next GOP alone switched with its parity.
- `mpc`: the look-ahead rule's throughput predictor (mpc_predictor) and the buffer reservoir as a constraint
  (mpc_buffer_constraint).

Rows: a rule under one setting, means over the generated trace sets x two buffers (16 traces each). "Cells won":
of those set x buffer cells, how many meet the ABR targets against the best classic rule of the cell (the one of
throughput, BOLA, BOLA-E and dynamic with the highest nominal QoE): nominal QoE >= 1.05x, rebuffering and switches
no more.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import subprocess
import tempfile
from pathlib import Path

from bench.streaming.abr import BUFFERS, SECONDS, SETS, long_ladder, packed_scene, run, trace_set
from stgs.client.abr import AbrSettings
from stgs.harness.ladder import load_ladder
from stgs.tree import MANIFEST

ROBUST_MPC_PSNR = {"mpc_predictor": "harmonic", "mpc_buffer_constraint": False, "mpc_utility": "psnr"}
"""The look-ahead rule as it was when the hysteresis was set: RobustMPC's predictor, the reservoir only charged,
rendered PSNR as its utility."""
GROUPS = {
    "stability": [
        ("throughput", "next GOP only, no headroom (before)", {"sustained_gops": 1, "switch_up_headroom": 0.0}),
        ("throughput", "sustained over 4 GOPs, no headroom", {"switch_up_headroom": 0.0}),
        ("throughput", "sustained over 4 GOPs, headroom 0.1 (default)", {}),
        ("throughput", "sustained over 4 GOPs, headroom 0.2", {"switch_up_headroom": 0.2}),
        ("dynamic", "next GOP only, no headroom (before)", {"sustained_gops": 1, "switch_up_headroom": 0.0}),
        ("dynamic", "sustained over 4 GOPs, headroom 0.1 (default)", {}),
        ("bola", "next GOP only (before)", {"sustained_gops": 1}),
        ("bola", "sustained over 4 GOPs (default)", {}),
        ("mpc", "margin 0 dB (before)", {**ROBUST_MPC_PSNR, "mpc_switch_margin_s": 0.0}),
        ("mpc", "margin 0.5 dB (default)", ROBUST_MPC_PSNR),
        ("mpc", "margin 1 dB", {**ROBUST_MPC_PSNR, "mpc_switch_margin_s": 0.1}),
        ("mpc", "margin 2 dB", {**ROBUST_MPC_PSNR, "mpc_switch_margin_s": 0.2}),
    ],
    "mpc": [
        (rule, f"{predictor}{', buffer constraint' if constraint else ''}{label}",
         {"mpc_predictor": predictor, "mpc_buffer_constraint": constraint, **extra})
        for rule, label, extra in (("mpc", ", PSNR utility", {"mpc_utility": "psnr"}),
                                   ("mpc", ", bit-rate utility", {"mpc_utility": "bitrate"}))
        for constraint in (False, True)
        for predictor in ("harmonic", "error-bound", "quantile", "ewma-lower")
    ],
}
CLASSIC = ("throughput", "bola", "bola-e", "dynamic")


def cells_won(cells: list[dict], best: list[dict]) -> int:
    """How many cells meet the targets against their best classic rule."""
    return sum(c["qoe_nominal"] >= 1.05 * b["qoe_nominal"] and c["rebuffer_pct"] <= b["rebuffer_pct"]
               and c["switches"] <= b["switches"] for c, b in zip(cells, best, strict=True))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dash", type=Path, help="a packaged scene (default: pack bench.streaming.abr's)")
    parser.add_argument("--group", choices=sorted(GROUPS), default="mpc", help="the settings to compare")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="stgs-bench-abr-settings-") as tmp:
        dash = args.dash or packed_scene(Path(tmp))
        base = load_ladder(str(dash))
        ladder = long_ladder(base, (dash / MANIFEST).read_text(), SECONDS)
        top_kbps = ladder.rung_kbps(-1)
        traces = {ts.name: trace_set(ts, top_kbps, Path(tmp)) for ts in SETS}
        keys = [(ts, b) for ts in SETS for b in BUFFERS]
        classic = {rule: [run(ladder, traces[ts.name], ts, b, rule, AbrSettings()) for ts, b in keys]
                   for rule in CLASSIC}
        best = [max((classic[rule][i] for rule in CLASSIC), key=lambda c: c["qoe_nominal"]) for i in range(len(keys))]
        print("| rule | setting | QoE (nominal) | QoE (sizes) | QoE (PSNR) | rebuffer % | switches | cells won |")
        print("|---|---|---|---|---|---|---|---|")

        def row(rule: str, label: str, cells: list[dict]) -> None:
            m = {key: statistics.mean(c[key] for c in cells) for key in cells[0]}
            print(f"| {rule} | {label} | {m['qoe_nominal']:.3f} | {m['qoe_size']:.3f} | {m['qoe_psnr']:.2f} "
                  f"| {m['rebuffer_pct']:.2f} | {m['switches']:.1f} | {cells_won(cells, best)}/{len(keys)} |",
                  flush=True)

        for rule in CLASSIC:
            row(rule, "default settings", classic[rule])
        for rule, label, overrides in GROUPS[args.group]:
            settings = dataclasses.replace(AbrSettings(), **overrides)
            row(rule, label, [run(ladder, traces[ts.name], ts, b, rule, settings) for ts, b in keys])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"\ncommit {commit}, {platform.processor() or platform.machine()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
