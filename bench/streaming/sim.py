"""Simulation fidelity vs cost (`stgs bench sim`): the simulator and the emulator on the same scenarios.

For each scenario: QoE, stall time and QP decisions of the discrete-event
simulator and of the emulator (real player + real server through the shaping
proxy, real time, no decoding), and playbacks per second of each engine.
"""

from __future__ import annotations

import platform
import tempfile
import time
from pathlib import Path

from stgs.harness.emulate import emulate
from stgs.harness.ladder import Ladder, load_ladder
from stgs.harness.report import metrics
from stgs.harness.scenario import scenario_from_dict
from stgs.harness.sim import simulate
from stgs.packager import PackConfig, pack
from stgs.synth import SynthConfig, synthesize

SCENE = SynthConfig(grid_side=32, num_gops=6, gop_size=10, fps=10.0, width=64, height=48, num_cameras=2,
                    fit_steps=100)
"""Six one-second GOPs of 1,024 Gaussians."""
SIM_REPEATS = 200
SCALED = 4.0
"""Speed of the scaled-time emulation."""


def scenarios(ladder: Ladder) -> dict[str, dict]:
    """Named effect sets scaled to the scene's rates (kf: the floor rung's keyframe kbit/s, top: the top rung's
    keyframe + features)."""
    T = ladder.pres.segment_seconds
    kf = max(ladder.rung_keyframe_bytes(0)) * 8 / T / 1e3  # the floor rung's keyframes
    top = (max(ladder.rung_keyframe_bytes(-1)) + max(ladder.media_bytes[ladder.pres.ladder[-1].rep_id])) * 8 / T / 1e3
    return {
        "ample (10x top)": {"bandwidth": {"kbps": 10 * top}},
        "tight (1.3x keyframe)": {"bandwidth": {"kbps": 1.3 * kf}},
        "starved (0.6x keyframe)": {"bandwidth": {"kbps": 0.6 * kf}},
        "step down at 2.5 s": {"bandwidth": {"steps": [[0, 10 * top], [2.5, 1.2 * kf]]}},
        "latency 80 ms + jitter 20 ms": {"bandwidth": {"kbps": 3 * top}, "latency_ms": 80, "jitter_ms": 20},
        "outage 1.5-3 s": {"bandwidth": {"kbps": 3 * top}, "outages": [[1.5, 3.0]]},
        "loss 2 % + 40 ms": {"bandwidth": {"kbps": 3 * top}, "loss": 0.02, "latency_ms": 40},
        "3 competing clients": {"bandwidth": {"kbps": 4 * top}, "competing": 3},
    }


def main(dash: Path | None, rule: str = "dynamic") -> int:
    with tempfile.TemporaryDirectory(prefix="stgs-bench-sim-") as tmp:
        if dash is None:
            print("synthesising and packing a 6-GOP scene ...", flush=True)
            synthesize(SCENE, Path(tmp) / "model", progress=False)
            pack(Path(tmp) / "model", Path(tmp) / "dash", PackConfig(ladder="fixed"), progress=False)
            dash = Path(tmp) / "dash"
        ladder = load_ladder(str(dash))
        rows = []
        for name, effects in scenarios(ladder).items():
            sc = scenario_from_dict({"scene": str(dash), "abr": [rule], "effects": effects, "name": name},
                                    name, Path("."))
            start = time.perf_counter()
            for _ in range(SIM_REPEATS):
                sim = simulate(ladder, sc, rule)
            sim_rate = SIM_REPEATS / (time.perf_counter() - start)
            start = time.perf_counter()
            emu = emulate(sc, rule)
            emu_rate = 1 / (time.perf_counter() - start)
            start = time.perf_counter()
            fast = emulate(sc, rule, speed=SCALED)
            fast_rate = 1 / (time.perf_counter() - start)
            ms, me = metrics(sim, ladder, sc.effects), metrics(emu, ladder, sc.effects)
            mf = metrics(fast, ladder, sc.effects)
            same = sum(a == b for a, b in zip(ms["qps"], me["qps"], strict=False))
            q = "qoe_nominal"
            rows.append(f"| {name} | {ms[q]:.3f} | {me[q]:.3f} | {mf[q]:.3f} | {ms['stall_s']:.2f} | "
                        f"{me['stall_s']:.2f} | {mf['stall_s']:.2f} | {ms['startup_delay_s']:.2f} / "
                        f"{me['startup_delay_s']:.2f} | {same}/{len(me['qps'])} | {sim_rate:,.0f} | {emu_rate:.3f} | "
                        f"{fast_rate:.3f} |")
    print(f"\nMachine: {platform.machine()}, {platform.processor() or 'cpu'}; rule {rule}; the simulator's rate is "
          f"the mean of {SIM_REPEATS} runs, the emulator's one real-time run and one at x{SCALED:g} (no decoding; "
          "each includes starting stgs serve).\n")
    print(f"| scenario | QoE sim | QoE emulated | QoE emulated x{SCALED:g} | stall s sim | stall s emulated | "
          f"stall s emulated x{SCALED:g} | start-up s sim / emu | same QP decisions (sim, emu) | sim playbacks/s | "
          f"emulated playbacks/s | emulated x{SCALED:g} playbacks/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(r)
    return 0
