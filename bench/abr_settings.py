"""The experiment that sets the ABR hysteresis (AbrSettings.sustained_gops, switch_up_headroom, mpc_switch_margin_s):
each setting over bench.abr's scene and trace sets, QoE against switches (`python -m bench.abr_stability`, prints
Markdown for docs/BENCHMARKS.md, "ABR rules over trace sets").

The scene is bench.abr's: the `demo` scene's two GOPs repeated, so every rung's GOPs alternate in size, the case
where deciding on the next GOP alone switched with its parity. Rows: a rule under one setting, means over the three
generated trace sets x two buffers (16 traces each); the per-cell figures are in the full run of bench.abr.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import subprocess
import tempfile
from pathlib import Path

from bench.abr import BUFFERS, SECONDS, SETS, long_ladder, packed_scene, run, trace_set
from stgs.client.abr import AbrSettings
from stgs.harness.ladder import load_ladder
from stgs.tree import MANIFEST

VARIANTS = [
    ("throughput", "next GOP only, no headroom (before)", {"sustained_gops": 1, "switch_up_headroom": 0.0}),
    ("throughput", "sustained over 4 GOPs, no headroom", {"switch_up_headroom": 0.0}),
    ("throughput", "sustained over 4 GOPs, headroom 0.1 (default)", {}),
    ("throughput", "sustained over 4 GOPs, headroom 0.2", {"switch_up_headroom": 0.2}),
    ("dynamic", "next GOP only, no headroom (before)", {"sustained_gops": 1, "switch_up_headroom": 0.0}),
    ("dynamic", "sustained over 4 GOPs, headroom 0.1 (default)", {}),
    ("bola", "next GOP only (before)", {"sustained_gops": 1}),
    ("bola", "sustained over 4 GOPs (default)", {}),
    ("mpc", "margin 0 dB (before)", {"mpc_switch_margin_s": 0.0}),
    ("mpc", "margin 0.5 dB (default)", {}),
    ("mpc", "margin 1 dB", {"mpc_switch_margin_s": 0.1}),
    ("mpc", "margin 2 dB", {"mpc_switch_margin_s": 0.2}),
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dash", type=Path, help="a packaged scene (default: pack bench.abr's)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="stgs-bench-abr-stability-") as tmp:
        dash = args.dash or packed_scene(Path(tmp))
        base = load_ladder(str(dash))
        ladder = long_ladder(base, (dash / MANIFEST).read_text(), SECONDS)
        top = ladder.pres.ladder[-1].rep_id
        top_kbps = (statistics.mean(ladder.keyframe_bytes) + statistics.mean(ladder.media_bytes[top])) * 8 \
            / ladder.pres.segment_seconds / 1e3
        traces = {ts.name: trace_set(ts, top_kbps, Path(tmp)) for ts in SETS}
        print("| rule | setting | QoE (nominal) | QoE (sizes) | QoE (PSNR) | rebuffer % | switches |")
        print("|---|---|---|---|---|---|---|")
        for rule, label, overrides in VARIANTS:
            settings = dataclasses.replace(AbrSettings(), **overrides)
            cells = [run(ladder, traces[ts.name], ts, b, rule, settings) for ts in SETS for b in BUFFERS]
            m = {key: statistics.mean(c[key] for c in cells) for key in cells[0]}
            print(f"| {rule} | {label} | {m['qoe_nominal']:.3f} | {m['qoe_size']:.3f} | {m['qoe_psnr']:.2f} "
                  f"| {m['rebuffer_pct']:.2f} | {m['switches']:.1f} |", flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"\ncommit {commit}, {platform.processor() or platform.machine()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
