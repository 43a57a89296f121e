"""Decision vectors: what an ABR rule saw and decided at every GOP of a simulated playback, for the web player's
ports of the rules (web/src/abr) to replay under Node and match rung for rung.

One contract, two implementations: the Python rules in stgs.client.abr are the reference; the simulator records
each AbrState a rule is handed and the Decision it returns, in order (a stateful rule, BOLA-E's placeholder or
mpc's error history, sees the same sequence in the replay), and tests/web/test_contracts.py replays them.

    python -m stgs.harness.vectors SCENE_DIR OUT.json     # every rule over FIXED_TRACES
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from stgs.client.abr import RULES, AbrRule, AbrSettings, AbrState, Decision
from stgs.client.abr.state import MPC_PREDICTORS
from stgs.fsio import atomic_write_bytes
from stgs.harness.ladder import Ladder, load_ladder
from stgs.harness.scenario import Scenario, scenario_from_dict
from stgs.harness.sim import Simulation

FIXED_TRACES: dict[str, list[list[float]]] = {
    "steady-high": [[0, 3.0]],
    "falling": [[0, 1.6], [1.5, 1.05], [3, 0.9], [4, 1.3]],
    "oscillating": [[0, 1.4], [0.7, 0.6], [1.4, 1.2], [2.1, 0.95], [2.8, 2.0], [3.5, 0.7], [4.2, 1.1]],
    "scarce": [[0, 0.5]],
    "edge": [[0, 1.0]],
}
"""Bandwidth steps the vectors are recorded over: [second, rate], the rate a multiple of the scene's full rate
(keyframe @bandwidth + the top rung's), so each shape crosses the rungs of any ladder: ample, a fall, swings,
starvation, and exactly the top rate."""


MPC_VARIANTS = [AbrSettings(mpc_predictor=p) for p in MPC_PREDICTORS if p != AbrSettings().mpc_predictor] + \
    [AbrSettings(mpc_buffer_constraint=not AbrSettings().mpc_buffer_constraint),
     AbrSettings(mpc_utility="psnr" if AbrSettings().mpc_utility == "bitrate" else "bitrate")]
"""The look-ahead rule's other predictors, its other buffer-target mode and its other utility, recorded beside every
rule's default."""


def state_json(state: AbrState) -> dict:
    """An AbrState as the TypeScript AbrState (camelCase, plain numbers)."""
    return {
        "bandwidths": list(state.bandwidths), "segmentS": state.segment_s, "bufferS": state.buffer_s,
        "bufferCapacityS": state.buffer_capacity_s,
        "samples": [{"bytes": s.bytes, "seconds": s.seconds, "ttfb": s.ttfb} for s in state.samples],
        "keyframeBits": state.keyframe_bits,
        "segmentBits": None if state.segment_bits is None else [float(b) for b in state.segment_bits],
        "current": state.current, "roundTrips": state.round_trips, "keyframeFetched": state.keyframe_fetched,
        "waitedS": state.waited_s,
        "upcoming": [{"keyframeBits": u.keyframe_bits, "segmentBits": [float(b) for b in u.segment_bits],
                      "psnr": None if u.psnr is None else [float(p) for p in u.psnr]} for u in state.upcoming],
        "playing": state.playing,
    }


def settings_json(settings: AbrSettings) -> dict:
    """AbrSettings as the TypeScript settings tree (camelCase keys)."""
    def camel(name: str) -> str:
        head, *rest = name.split("_")
        return head + "".join(p.upper() if p in ("s",) else p.capitalize() for p in rest)
    return {camel(f.name): getattr(settings, f.name) for f in dataclasses.fields(settings)}


class RecordingRule:
    """A rule that records every state it is handed and what the wrapped rule decided."""

    def __init__(self, rule: AbrRule):
        self.rule = rule
        self.name = rule.name
        self.steps: list[dict] = []

    def choose(self, state: AbrState) -> Decision:
        decision = self.rule.choose(state)
        self.steps.append({"state": state_json(state), "decision": decision.to_json()})
        return decision


def decision_vector(ladder: Ladder, scenario: Scenario, rule: str, settings: AbrSettings | None = None) -> dict:
    """One simulated playback of `rule`, with every decision's input and output."""
    settings = settings or AbrSettings()
    sim = Simulation(ladder, scenario, rule, settings)
    recorder = RecordingRule(sim.schedule.rule)
    sim.schedule.rule = recorder
    sim.run()
    return {"rule": rule, "scenario": scenario.name, "settings": settings_json(settings), "steps": recorder.steps}


def decision_vectors(scene: Path, traces: dict[str, list[list[float]]] = FIXED_TRACES) -> list[dict]:
    """Every rule over every trace on a packaged scene's AV1 set (the browsers' feature set), and mpc under
    MPC_VARIANTS."""
    ladder = load_ladder(str(scene), "av1")
    full_kbps = ladder.pres.ladder[-1].total_bandwidth / 1e3
    vectors = []
    for name, shape in traces.items():
        steps = [[t, rate * full_kbps] for t, rate in shape]
        doc = {"name": name, "scene": str(scene), "codec": "av1", "effects": {"bandwidth": {"steps": steps},
                                                                              "latency_ms": 20}}
        scenario = scenario_from_dict(doc, name, Path(scene))
        vectors += [decision_vector(ladder, scenario, rule) for rule in RULES]
        vectors += [decision_vector(ladder, scenario, "mpc", settings) for settings in MPC_VARIANTS]
    return vectors


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m stgs.harness.vectors SCENE_DIR OUT.json", file=sys.stderr)
        return 2
    vectors = decision_vectors(Path(argv[0]))
    atomic_write_bytes(Path(argv[1]), json.dumps({"vectors": vectors}).encode())
    print(f"{sum(len(v['steps']) for v in vectors)} decisions of {len(vectors)} playbacks -> {argv[1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
