"""The throughput simulation harness: hand-computable scenarios, traces, effects, sim vs emulation, bad input."""

from __future__ import annotations

import dataclasses
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stgs.client.abr import AbrSettings
from stgs.client.manifest import Presentation
from stgs.errors import StgsError
from stgs.harness.decode import DecoderModel
from stgs.harness.ladder import Ladder, load_ladder
from stgs.harness.network import Network
from stgs.harness.report import metrics, sabre_manifest, timeline
from stgs.harness.scenario import Effects, scenario_from_dict
from stgs.harness.sim import simulate
from stgs.harness.trace import constant, load_trace, steps
from tests.conftest import run_stgs as stgs
from tests.harness.conftest import SCENE

EXAMPLE = (Path(__file__).resolve().parents[2] / "manifests" / "example.mpd").read_bytes()


def hand_ladder(gops: int = 5, keyframe: int = 125_000, media=(12_500, 25_000, 50_000, 100_000, 200_000),
                init: int = 1_000) -> Ladder:
    """The example MPD's 1-second GOPs and five QPs with sizes we choose (ascending rung order qp32 ... qp16)."""
    mpd = EXAMPLE.replace(b'mediaPresentationDuration="PT2S"', f'mediaPresentationDuration="PT{gops}S"'.encode())
    pres = Presentation.parse(mpd, "http://h/manifest.mpd")
    reps = [r.rep_id for r in pres.ladder]
    return Ladder(pres, [keyframe] * gops, {r: [m] * gops for r, m in zip(reps, media, strict=True)},
                  dict.fromkeys(reps, init), {r: [40.0 + i] * gops for i, r in enumerate(reps)}, None)


STATIC_SET = (b'<AdaptationSet id="0" contentType="application" mimeType="application/vnd.streamstgs.static">'
              b'<SupplementalProperty schemeIdUri="urn:streamstgs:static:2026" '
              b'value="version=1;capacity=4096;grid_side=64;sh_degree=0"/>'
              b'<SegmentTemplate media="static/layer.stgl" timescale="1" duration="5" startNumber="0"/>'
              b'<Representation id="static" bandwidth="400000"/></AdaptationSet>')


def layered_mpd(gops: int) -> bytes:
    """The example MPD with `gops` 1-second GOPs and a static layer (a format-2 presentation)."""
    data = EXAMPLE.replace(b'mediaPresentationDuration="PT2S"', f'mediaPresentationDuration="PT{gops}S"'.encode())
    head, sep, tail = data.partition(b"<Period")
    period_end = tail.index(b">") + 1
    return head + sep + tail[:period_end] + STATIC_SET + tail[period_end:]


def layered_ladder(static: int = 250_000, gops: int = 5) -> Ladder:
    """hand_ladder's sizes with a static layer of `static` bytes (a format-2 presentation)."""
    plain = hand_ladder(gops)
    pres = Presentation.parse(layered_mpd(gops), "http://h/manifest.mpd")
    return Ladder(pres, plain.keyframe_bytes, plain.media_bytes, plain.init_bytes, plain.psnr, None, static)


def test_the_static_layer_is_fetched_once_and_counts_in_startup():
    fx = {"bandwidth": {"kbps": 500}}
    log = simulate(layered_ladder(), scenario(fx, qp=32), "throughput")
    # 2 Mbit of static layer at 0.5 Mbit/s (4 s), then GOP 0 as in the format-1 case (1.108 Mbit: 2.216 s).
    assert log["startup_delay_s"] == pytest.approx(4.0 + 2.216)
    assert log["static_bytes"] == 250_000 and log["gops"][0]["requests"][0]["kind"] == "static"
    assert sum(r["kind"] == "static" for g in log["gops"] for r in g["requests"]) == 1
    # A slow static decode holds the first GOP's features back: ready when the layer is decoded (4 + 3 s).
    slow = simulate(layered_ladder(), scenario(fx, qp=32, decode={"static_ms": 3000}), "throughput")
    assert slow["startup_delay_s"] == pytest.approx(7.0) and slow["gops"][0]["static_decode_s"] == 3.0
    # Started at GOP 3, the static layer is still fetched first, once.
    later = simulate(layered_ladder(), scenario(fx, qp=32, start_s=3.0), "throughput")
    assert [g["index"] for g in later["gops"]] == [3, 4] and later["static_bytes"] == 250_000
    assert later["gops"][0]["requests"][0]["kind"] == "static"
    # A static segment the server refuses ends the playback before any GOP.
    refused = simulate(layered_ladder(), scenario({**fx, "faults": [{"path": "layer.stgl", "status": 404}]},
                                                  qp=32), "throughput")
    assert refused["error"].startswith("static layer") and refused["gops_played"] == 0


def test_sabre_export_budgets_the_static_layer_in_segment_0():
    doc = sabre_manifest(layered_ladder(static=10_000, gops=3))
    media = (12_500, 25_000, 50_000, 100_000, 200_000)
    assert doc["segment_sizes_bits"][0] == [(125_000 + m + 1_000 + 10_000) * 8 for m in media]
    assert doc["segment_sizes_bits"][1] == [(125_000 + m) * 8 for m in media]
    extra = doc["streamstgs"]
    assert extra["static_layer_bits"] == 80_000 and extra["static_layer_budget"] == "segment 0"
    assert extra["first_segment_requests"] == 4
    assert sabre_manifest(hand_ladder(gops=3))["streamstgs"]["static_layer_bits"] == 0


def scenario(effects: dict, **kw):
    return scenario_from_dict({"scene": "unused", "effects": effects, **kw}, "test", Path("."))


def test_bandwidth_far_above_the_top_rung_plays_the_top_qp_without_stalls():
    ladder = hand_ladder()
    log = simulate(ladder, scenario({"bandwidth": {"kbps": 100_000}}), "throughput")
    # the first decision already has the keyframe's throughput sample: top rung from GOP 0
    assert [g["qp"] for g in log["gops"]] == [16] * 5
    assert log["stalls"] == {"count": 0, "total_s": 0.0}


def test_bandwidth_below_the_keyframe_rate_stalls_exactly():
    ladder = hand_ladder()
    log = simulate(ladder, scenario({"bandwidth": {"kbps": 500}}, qp=32), "throughput")
    # GOP 0: (1 Mbit keyframe + 8 kbit init + 0.1 Mbit features) / 0.5 Mbit/s = 2.216 s = start-up.
    # every later GOP takes 1.1 / 0.5 = 2.2 s to download and is due 1 s after the previous one: 1.2 s stall each.
    assert log["startup_delay_s"] == pytest.approx(2.216)
    assert log["stalls"]["count"] == 4
    assert log["stalls"]["total_s"] == pytest.approx(4 * 1.2)
    assert [g["stall_s"] for g in log["gops"]] == pytest.approx([0, 1.2, 1.2, 1.2, 1.2])
    report = metrics(log, ladder, scenario({"bandwidth": {"kbps": 500}}).effects)
    assert report["rebuffer_ratio"] == pytest.approx(4.8 / (5 + 4.8))
    assert report["mean_quality_db"] == 40.0 and report["switches"] == 0


def test_three_qoes_named_apart_and_a_steady_rung_pays_no_switch_penalty_at_nominal_rates():
    ladder = hand_ladder(gops=4)
    top = ladder.pres.ladder[-1].rep_id
    ladder.media_bytes[top] = [150_000, 250_000, 150_000, 250_000]  # the pinned rung's GOPs alternate in size
    sc = scenario({"bandwidth": {"kbps": 100_000}}, qp=16)
    report = metrics(simulate(ladder, sc, "throughput"), ladder, sc.effects)
    assert report["qps"] == [16] * 4 and report["stall_s"] == 0
    nominal = (125_000 + 200_000) * 8 / 1e6  # keyframe + the rung's mean, Mbit/s over 1-second GOPs
    assert report["qoe_nominal"] == pytest.approx(nominal)  # no switch penalty: one number per rung
    sizes = [(125_000 + m) * 8 / 1e6 for m in ladder.media_bytes[top]]
    assert report["qoe_size"] == pytest.approx((sum(sizes) - 3 * 0.8) / 4)  # three |ΔR| of 0.8 Mbit/s charged
    assert report["qoe_psnr"] == pytest.approx(44.0)  # hand_ladder's top rung renders at 44 dB, steadily


def test_gops_alternating_in_size_give_at_most_one_switch_on_a_constant_trace():
    ladder = hand_ladder(gops=30)
    for rep in ladder.media_bytes:  # every rung's GOPs alternate 0.6x / 1.4x in size
        ladder.media_bytes[rep] = [round(m * (0.6 if k % 2 else 1.4)) for k, m in enumerate(ladder.media_bytes[rep])]
    for kbps in (1_200, 1_500, 1_800, 2_000, 2_300, 2_600, 3_000, 3_300, 4_000):  # across the ladder
        log = simulate(ladder, scenario({"bandwidth": {"kbps": kbps}}, buffer_s=6.0), "throughput")
        assert log["switches"] <= 1, (kbps, [g["qp"] for g in log["gops"]])
    sc = scenario({"bandwidth": {"kbps": 2_300}}, buffer_s=6.0)  # between qp20's GOPs (1.42 / 2.58 Mbit/s)
    # deciding on the next GOP alone, without headroom, follows the parity
    parity = simulate(ladder, sc, "throughput", AbrSettings(sustained_gops=1, switch_up_headroom=0.0))
    assert parity["switches"] >= 10
    # DYNAMIC is the throughput rule at this buffer, but for its start-up cap, which dips once on the way up
    qps = [g["qp"] for g in simulate(ladder, sc, "dynamic")["gops"]]
    assert len(set(qps[4:])) == 1


def test_a_step_down_moves_the_throughput_rule_down_on_the_next_gop():
    ladder = hand_ladder(gops=6)
    sc = scenario({"bandwidth": {"steps": [[0, 20_000], [2.0, 800]]}})
    log = simulate(ladder, sc, "throughput")
    qps = [g["qp"] for g in log["gops"]]
    first_slow = next(i for i, g in enumerate(log["gops"]) if g["fetch_start_s"] >= 2.0)
    assert qps[first_slow - 1] == 16  # plenty before the step
    assert qps[first_slow] > qps[first_slow - 1]  # the next decision after the drop picks a lower rung


def test_the_first_gop_does_not_abandon_itself_on_a_high_latency_link():
    """4 Mbit/s, 200-ms round trips: every rung the throughput rule picks arrives within a GOP. Measured from the
    request (round trip included) the first download looked slow and, with an empty buffer before start-up, was
    dropped after 0.2 s; measured on its body it goes on."""
    ladder = hand_ladder(gops=6)
    for rule in ("throughput", "dynamic", "mpc"):
        log = simulate(ladder, scenario({"bandwidth": {"kbps": 4000}, "latency_ms": 200}), rule)
        assert [g["abandoned_bytes"] for g in log["gops"]] == [0] * 6, rule
        assert log["gops"][0]["qp"] < 32, rule  # GOP 0 above the lowest rung: the keyframe's sample was believed
        assert log["stalls"]["count"] == 0, rule


def test_keyframe_and_features_share_one_round_trip():
    """After the first GOP, keyframe and features are asked for together: a GOP costs one round trip, not two."""
    ladder = hand_ladder(gops=4)
    effects = {"bandwidth": {"kbps": 4000}, "latency_ms": 100}
    log = simulate(ladder, scenario(effects, qp=32), "throughput")
    # GOP 0: the pinned rung's init segment, then keyframe + media together: 2 round trips + 1.108 Mbit / 4 Mbit/s
    assert log["gops"][0]["download_s"] == pytest.approx(0.2 + 1.108 / 4)
    # later GOPs: one round trip, then 1.1 Mbit
    assert [g["download_s"] for g in log["gops"][1:]] == pytest.approx([0.1 + 1.1 / 4] * 3)
    assert [r["kind"] for r in log["gops"][1]["requests"]] == ["keyframe", "media"]
    # an adaptive rule's first GOP fetches its keyframe first (its only throughput sample): 3 round trips there
    adaptive = simulate(ladder, scenario(effects), "throughput")
    assert [r["kind"] for r in adaptive["gops"][0]["requests"]] == ["keyframe", "init", "media"]
    assert [r["kind"] for r in adaptive["gops"][2]["requests"]][-2:] == ["keyframe", "media"]


def test_only_declared_effects_are_applied():
    ladder = hand_ladder()
    sc = scenario({"bandwidth": {"kbps": 2000}})
    assert sc.effects.active() == ["bandwidth"]
    rows = timeline(simulate(ladder, sc, "dynamic"), sc.effects)
    assert all(r["latency_ms"] == 0.0 and r["loss"] == 0.0 for r in rows)
    assert metrics(simulate(ladder, sc, "dynamic"), ladder, sc.effects)["active_effects"] == {
        "bandwidth": "constant bandwidth"}
    # and with nothing named at all, transfers are instant: start-up is zero
    assert simulate(ladder, scenario({}), "dynamic")["startup_delay_s"] == 0.0


def test_network_effects_by_hand():
    fx = Effects(bandwidth=constant(1000), latency_ms=100.0, outages=[(1.0, 2.0)], competing=1)
    net = Network(fx)
    assert net.round_trip() == pytest.approx(0.1)
    # 500 kbit/s fair share; 0.75 Mbit from t=0.5: 0.25 Mbit by 1.0, outage to 2.0, 0.5 Mbit more by 3.0
    assert net.finish(0.5, 750_000) == pytest.approx(3.0)
    lossy = Network(Effects(bandwidth=constant(1000), loss=0.2))
    assert lossy.finish(0.0, 800_000) == pytest.approx(1.0)  # (1 - 0.2) of 1 Mbit/s
    jitter = Network(Effects(latency_ms=50.0, jitter_ms=20.0), seed=3)
    draws = [jitter.round_trip() for _ in range(200)]
    assert min(draws) >= 0.03 - 1e-9 and max(draws) <= 0.07 + 1e-9
    again = Network(Effects(latency_ms=50.0, jitter_ms=20.0), seed=3)
    assert draws == [again.round_trip() for _ in range(200)]  # the scenario's seed fixes the jitter


def test_trace_formats_and_looping(tmp_path):
    (tmp_path / "t.json").write_text(json.dumps([{"duration_ms": 1000, "bandwidth_kbps": 300, "latency_ms": 20},
                                                 {"duration_ms": 500, "bandwidth_kbps": 900, "latency_ms": 20}]))
    (tmp_path / "t.log").write_text("0 1.5\n1 0.5\n")
    # Mahimahi: 1500-byte delivery opportunities in ms; 3 packets in 0-100 ms, none in 100-200, 1 at 250 (the end)
    (tmp_path / "mm.down").write_text("0\n40\n40\n250\n")
    (tmp_path / "t.csv").write_text("time_s,bandwidth_kbps\n0,2000\n2,400\n")
    sabre = load_trace(tmp_path / "t.json", "sabre")
    assert sabre.segment(0.2) == pytest.approx((300, 0.8)) and sabre.segment(1.2)[0] == 900
    assert sabre.segment(1.6)[0] == 300  # looped: period 1.5 s
    pensieve = load_trace(tmp_path / "t.log", "pensieve")
    assert pensieve.segment(0.5)[0] == 1500 and pensieve.segment(1.5)[0] == 500 and pensieve.segment(2.5)[0] == 1500
    assert load_trace(tmp_path / "t.log").kbps == pensieve.kbps  # two columns are sniffed as Pensieve's
    mm = load_trace(tmp_path / "mm.down")  # one integer per line: Mahimahi's
    assert mm.period == pytest.approx(0.25) and mm.times == pytest.approx([0, 0.1, 0.2])
    assert mm.kbps == pytest.approx([3 * 12_000 / 0.1 / 1e3, 0, 12_000 / 0.05 / 1e3])
    assert mm.segment(0.26)[0] == pytest.approx(360)  # looped after its last packet time
    with pytest.raises(StgsError, match="Pensieve's format"):
        load_trace(tmp_path / "t.log", "mahimahi")
    with pytest.raises(StgsError, match="Mahimahi's format"):
        load_trace(tmp_path / "mm.down", "pensieve")
    (tmp_path / "huge.down").write_text("0\n" + "9" * 400 + "\n")  # found by the fuzzer: was an OverflowError
    with pytest.raises(StgsError, match="packet time past"):
        load_trace(tmp_path / "huge.down")
    c = load_trace(tmp_path / "t.csv", "csv")
    assert c.segment(1.0)[0] == 2000 and c.segment(3.0)[0] == 400 and c.segment(4.5)[0] == 2000
    assert steps([[0, 5], [1, 7]]).segment(100)[0] == 7  # steps hold their last value


def test_sabre_export():
    ladder = hand_ladder(gops=3)
    doc = sabre_manifest(ladder)
    assert doc["segment_duration_ms"] == 1000
    media = (12_500, 25_000, 50_000, 100_000, 200_000)
    # segment 0 carries its rung's init segment (1,000 bytes), as our player fetches it before GOP 0's features
    assert doc["segment_sizes_bits"][0] == [(125_000 + m + 1_000) * 8 for m in media]
    assert doc["segment_sizes_bits"][1] == [(125_000 + m) * 8 for m in media]
    assert doc["bitrates_kbps"][0] == pytest.approx((125_000 + 12_500) * 8 / 1e3)  # media only, as @bandwidth
    extra = doc["streamstgs"]
    assert extra["init_segment_bits"] == [8_000] * 5 and extra["requests_per_segment"] == 1


@pytest.mark.parametrize("body,message", [
    ('scene = "x"\n[effects]\nwind = 3\n', "unknown effect(s) ['wind']"),
    ('scene = "x"\n[effects]\nbandwidth = { kbps = -5 }\n', "'kbps' must be >= 0"),
    ('scene = "x"\n[effects]\nbandwidth = { trace = "bad.log" }\n', "malformed pensieve trace"),
    ('scene = "x"\n[effects]\nbandwidth = { trace = "empty.csv" }\n', "the trace is empty"),
    ('scene = "x"\n[effects]\nbandwidth = { steps = [[0, 0]] }\n', None),
    ('scene = "x"\nabr = ["magic"]\n', "'abr' must list rules"),
    ('scene = "x"\n[effects]\nloss = 1.5\n', "'loss' must be below 1"),
    ('scene = \n', "cannot read scenario"),
    ('scene = "x"\n[decode]\nframe_ms = -1\n', "decode 'frame_ms' (or a table by Representation id) must be"),
    ('scene = "x"\n[decode]\nframe_ms = { qp16 = "fast" }\n', "decode 'frame_ms.qp16' must be a number"),
    ('scene = "x"\n[decode]\nring_frames = 0\n', "'ring_frames' must be an integer >= 1"),
    ('scene = "x"\n[decode]\nrender_ahead = -1\n', "'render_ahead' must be an integer >= 0"),
    ('scene = "x"\n[decode]\nthreads = 2\n', "unknown decode key(s) ['threads']"),
])
def test_bad_scenarios_are_one_line(tmp_path, body, message):
    (tmp_path / "bad.log").write_text("0 1 2\n")
    (tmp_path / "empty.csv").write_text("time_s,bandwidth_kbps\n")
    (tmp_path / "s.toml").write_text(body)
    result = stgs("sim", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("stgs: "), result.stderr
    if message:
        assert message in lines[0]


def test_a_scenario_is_read_without_torch():
    """`stgs sim` validates its scenario before the player's heavy imports, so a mistake costs no start-up."""
    code = "import sys, stgs.harness.scenario; print(sorted({'torch', 'av'} & set(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


def rates(ladder: Ladder) -> tuple[float, float]:
    """(keyframe kbit/s, top GOP kbit/s) of the scene."""
    T = ladder.pres.segment_seconds
    top = ladder.pres.ladder[-1].rep_id
    kf = max(ladder.keyframe_bytes) * 8 / T / 1e3
    return kf, kf + max(ladder.media_bytes[top]) * 8 / T / 1e3


def test_simulation_and_emulation_agree(packed):
    from stgs.harness.emulate import emulate

    ladder = load_ladder(str(packed))
    kf, top = rates(ladder)
    cases = [
        ({"bandwidth": {"kbps": 20 * top}}, "dynamic", None),
        ({"bandwidth": {"kbps": 0.5 * kf}}, "throughput", 32),
        ({"bandwidth": {"steps": [[0, 20 * top], [1.2, 0.6 * kf]]}, "latency_ms": 20}, "throughput", None),
    ]
    for effects, rule, qp in cases:
        sc = scenario_from_dict({"scene": str(packed), "abr": [rule], "effects": effects,
                                 **({"qp": qp} if qp else {})}, "agree", Path("."))
        sim, emu = simulate(ladder, sc, rule), emulate(sc, rule)
        assert [g["qp"] for g in sim["gops"]] == [g["qp"] for g in emu["gops"]], (effects, sim, emu)
        s, e = sim["stalls"]["total_s"], emu["stalls"]["total_s"]
        assert sim["stalls"]["count"] == emu["stalls"]["count"]
        assert abs(s - e) <= max(0.1 * s, 0.05), (effects, s, e)


def paced(seconds: float, started: float) -> None:
    """Sleep until `seconds` have passed since `started`: the real work inside a paced call costs no extra time
    (as long as it takes less), so the emulated player's decode costs are the scenario's on any machine."""
    time.sleep(max(0.0, seconds - (time.perf_counter() - started)))


@pytest.mark.parametrize("ahead", [0, 2])
def test_the_per_frame_decode_model_agrees_with_emulation_when_decoding_is_the_bottleneck(packed, monkeypatch,
                                                                                           ahead):
    """Each feature frame takes 235 ms to decode against a 167 ms frame interval: the real player falls behind
    at every boundary (stalls) and, rendering each frame in its slot, within every GOP (dropped frames); the
    simulator's model of the same pipeline must predict the stall time within 10 % and the drops within 2,
    with and without rendering ahead (whose head start after each stall absorbs the drops here).

    The decode costs are paced and chosen off the model's edges: at 250 ms a GOP's end coincides with a
    feature frame's completion, and a millisecond of jitter decides whether one more frame (250 ms) is decoded
    before the next GOP's. A pace is a floor, not a promise: on a loaded machine a decode can take longer, so
    the simulator is given what the decodes of this emulation actually cost (their mean), not the pace."""
    from stgs.codec import stream
    from stgs.codec.keyframe import KeyframeSegment
    from stgs.harness.emulate import emulate

    frame_s, keyframe_s = 0.235, 0.1
    real_frames, real_keyframe = stream.iter_frames, KeyframeSegment.decode

    frame_costs: list[float] = []
    keyframe_costs: list[float] = []

    def slow_frames(*args, **kwargs):  # a decoder this much slower than the machine's
        frames = real_frames(*args, **kwargs)
        while True:
            started = time.perf_counter()
            frame = next(frames, None)
            if frame is None:
                return
            paced(frame_s, started)
            frame_costs.append(time.perf_counter() - started)
            yield frame

    def slow_keyframe(*args, **kwargs):
        started = time.perf_counter()
        keyframe = real_keyframe(*args, **kwargs)
        paced(keyframe_s, started)
        keyframe_costs.append(time.perf_counter() - started)
        return keyframe

    monkeypatch.setattr(stream, "iter_frames", slow_frames)
    monkeypatch.setattr(KeyframeSegment, "decode", slow_keyframe)
    ladder = load_ladder(str(packed))
    _, top = rates(ladder)

    def scenario(frame_cost_s: float, keyframe_cost_s: float = keyframe_s):
        return scenario_from_dict({"scene": str(packed), "abr": ["throughput"], "qp": 32,
                                   "effects": {"bandwidth": {"kbps": 20 * top}},
                                   "decode": {"frame_ms": frame_cost_s * 1e3, "keyframe_ms": keyframe_cost_s * 1e3,
                                              "ring_frames": 4, "render_ahead": ahead}},
                                  "decode-bound", Path("."))

    sc = scenario(frame_s)
    paced_sim = simulate(ladder, sc, "throughput")
    for off in (0.98, 1.02):  # off an edge: 2 % of cost moves nothing by more than the tolerance below
        near = simulate(ladder, scenario(off * frame_s), "throughput")
        assert near["dropped_frames"] == paced_sim["dropped_frames"], off
        assert abs(near["stalls"]["total_s"] - paced_sim["stalls"]["total_s"]) <= \
            0.05 * paced_sim["stalls"]["total_s"], off
    emu = emulate(sc, "throughput", decode=True)
    assert frame_costs and keyframe_costs and min(frame_costs) >= frame_s and min(keyframe_costs) >= keyframe_s
    sim = simulate(ladder, scenario(statistics.mean(frame_costs), statistics.mean(keyframe_costs)), "throughput")
    s, e = sim["stalls"]["total_s"], emu["stalls"]["total_s"]
    assert s > 1.0 and sim["stalls"]["count"] == emu["stalls"]["count"] == SCENE.num_gops - 1
    assert abs(s - e) <= 0.1 * s, (s, e)
    assert abs(sim["dropped_frames"] - emu["dropped_frames"]) <= 2
    assert sim["dropped_frames"] > 0 if ahead == 0 else sim["dropped_frames"] == 0


def test_the_decode_model_by_hand():
    """G = 6 frames at 6 fps, W = 3, ring 4, 0.25 s per feature frame, everything downloaded at 0."""
    model = DecoderModel(ring=4, window=3, gop_size=6, fps=6.0)
    plan = model.plan(downloaded=0.0, slot=0.0, keyframe_s=0.1, frame_s=0.25)
    assert plan.keyframe_done == pytest.approx(0.1) and plan.features_start == 0.0  # side by side
    assert plan.ready == pytest.approx(3 * 0.25)  # the first window, the keyframe long done
    drops = model.start(plan, plan.ready)
    # feature frame j is decoded at 0.25 (j + 1) (the ring never fills: frames are released in time);
    # frame m (window m..m+2) is drawn if 0.25 (m + 3) < 0.75 + (m + 1) / 6: m = 0, 1 only
    assert drops == 4
    # the GOP ends at 1.75, when frame 6 is decoded: frame 7 is never decoded
    assert model.features_free == pytest.approx(1.75)
    nxt = model.plan(downloaded=0.0, slot=0.0, keyframe_s=0.1, frame_s=0.25)
    assert nxt.keyframe_done == pytest.approx(0.85)  # taken up once GOP 0 was ready
    assert nxt.features_start == pytest.approx(1.75) and nxt.ready == pytest.approx(2.5)
    # a static layer still decoding holds the GOP back, not its features
    late = DecoderModel(ring=4, window=3, gop_size=6, fps=6.0).plan(0.0, 0.0, 0.1, 0.25, not_before=2.0)
    assert late.features_start == 0.0 and late.ready == pytest.approx(2.0)


def test_scaled_time_emulation_agrees_too(packed):
    from stgs.harness.emulate import emulate

    ladder = load_ladder(str(packed))
    kf, _ = rates(ladder)
    sc = scenario_from_dict({"scene": str(packed), "abr": ["throughput"], "qp": 32,
                             "effects": {"bandwidth": {"kbps": 0.5 * kf}, "latency_ms": 40}}, "x4", Path("."))
    sim = simulate(ladder, sc, "throughput")
    emu = emulate(sc, "throughput", speed=4.0)  # a player clock at 1x against a 4x network would stall far less
    assert emu["engine"] == "emulate x4"
    assert [g["qp"] for g in sim["gops"]] == [g["qp"] for g in emu["gops"]]
    s, e = sim["stalls"]["total_s"], emu["stalls"]["total_s"]
    assert sim["stalls"]["count"] == emu["stalls"]["count"] >= 1
    assert abs(s - e) <= max(0.1 * s, 0.05), (s, e)


def test_cli_batch_and_load(packed, tmp_path):
    traces = tmp_path / "traces"
    traces.mkdir()
    (traces / "fast.log").write_text("0 50\n1 50\n")
    (traces / "slow.csv").write_text("time_s,bandwidth_kbps\n0,100\n1,150\n")
    (tmp_path / "s.toml").write_text(f'scene = "{packed}"\nabr = ["throughput", "bola"]\n'
                                     '[effects]\nbandwidth = {{ kbps = 1000 }}\n'.replace("{{", "{").replace("}}", "}"))
    out = tmp_path / "out"
    result = stgs("sim", str(tmp_path / "s.toml"), "--traces", str(traces), "--out", str(out),
                  "--export-sabre", str(tmp_path / "sabre.json"))
    assert result.returncode == 0, result.stderr
    rows = json.loads((out / "s.batch.json").read_text())
    assert len(rows) == 4 and {r["trace"] for r in rows} == {"fast.log", "slow.csv"}
    slow = [r for r in rows if r["trace"] == "slow.csv"]
    fast = [r for r in rows if r["trace"] == "fast.log"]
    assert min(r["stall_s"] for r in slow) > max(r["stall_s"] for r in fast)
    assert (out / "s.qoe_cdf.png").stat().st_size > 5000
    assert "| throughput (sim) | 2 |" in result.stdout
    assert len(json.loads((tmp_path / "sabre.json").read_text())["segment_sizes_bits"]) == 3
    result = stgs("sim", str(tmp_path / "s.toml"), "--load", "1,4", "--out", str(out))
    assert result.returncode == 0, result.stderr
    load = json.loads((out / "s.load.json").read_text())
    assert [r["clients"] for r in load] == [1, 4] and all(r["server_mb_s"] > 0 for r in load)


def test_single_scenario_writes_timeline_plot_and_summary(packed, tmp_path):
    (tmp_path / "s.toml").write_text(f'scene = "{packed}"\nabr = "dynamic"\n[effects]\nlatency_ms = 30\n')
    out = tmp_path / "out"
    result = stgs("sim", str(tmp_path / "s.toml"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "active effects {'latency_ms': 30}" in result.stdout
    assert (out / "s-sim-dynamic.png").stat().st_size > 5000
    csv_text = (out / "s-sim-dynamic.timeline.csv").read_text().splitlines()
    assert csv_text[0].startswith("index,rep,qp") and len(csv_text) == 4
    assert all(line.split(",")[-2] == "30.0" for line in csv_text[1:])  # latency_ms column
    assert dataclasses.is_dataclass(Effects())
    with pytest.raises(StgsError):
        load_ladder(str(tmp_path / "nothing"))



def fetch_trace(log: dict) -> list[tuple]:
    """Per GOP: its requests (kind, Representation, done/failed/abandoned) and decisions (rule, rung)."""
    def outcome(text: str) -> str:
        return "done" if text.split()[0].isdigit() else text.split()[0].rstrip(":")

    return [(g["index"], [(r["kind"], r["rep"], outcome(r["outcome"])) for r in g["requests"]],
             [(d["rule"], d["index"]) for d in g["decisions"]]) for g in log["gops"]]


@pytest.mark.parametrize("name, effects, rule, qp", [
    # a media segment the server refuses for good: fallback to the lowest rung for that GOP
    ("fallback", {"faults": [{"path": "qp16/seg_00001", "status": 404}]}, "throughput", 16),
    # a keyframe answered 503 twice, then served: two retries with backoff
    ("retries", {"faults": [{"path": "gop_00002", "status": 503, "times": 2}]}, "throughput", 32),
    # adaptive on a fast network, one transient failure of the top rung's segment
    ("adaptive", {"bandwidth": {"kbps": 100_000},
                  "faults": [{"path": "qp16/seg_00001", "status": 500, "times": 1}]}, "throughput", None),
])
def test_player_and_simulator_make_the_same_requests_and_decisions(packed, name, effects, rule, qp):
    from stgs.harness.emulate import emulate

    ladder = load_ladder(str(packed))
    sc = scenario_from_dict({"scene": str(packed), "abr": [rule], "effects": effects, **({"qp": qp} if qp else {})},
                            name, Path("."))
    sim, emu = simulate(ladder, sc, rule), emulate(sc, rule)
    trace = fetch_trace(sim)
    assert trace == fetch_trace(emu)
    assert sim["retries"] == emu["retries"] and sim["error"] is None and emu["error"] is None
    if name == "fallback":
        assert trace[1][1] == [("keyframe", "keyframes", "done"), ("media", "qp16", "failed"),
                               ("init", "qp32", "done"), ("media", "qp32", "done")]
        assert trace[1][2] == [("fixed", 2), ("fallback", 0)]
        assert [g["qp"] for g in sim["gops"]] == [16, 32, 16]
        assert "HTTP 404" in sim["gops"][1]["decisions"][1]["reason"]
    elif name == "retries":
        # keyframe and features are asked for together; the keyframe alone again after each backoff
        assert trace[2][1] == [("keyframe", "keyframes", "failed"), ("media", "qp32", "done"),
                               ("keyframe", "keyframes", "failed"), ("keyframe", "keyframes", "done")]
        assert sim["retries"] == 2
    else:
        assert trace[1][1] == [("keyframe", "keyframes", "done"), ("media", "qp16", "failed"),
                               ("media", "qp16", "done")]
        assert trace[0][2] == [("throughput", 2)] and sim["retries"] == 1
    assert any("decode" in line for line in sim["not_modelled"])


def test_a_refused_lowest_rung_ends_both_playbacks_at_the_same_gop(packed):
    from stgs.client import PlaybackError
    from stgs.harness.emulate import emulate

    ladder = load_ladder(str(packed))
    sc = scenario_from_dict({"scene": str(packed), "abr": ["throughput"], "qp": 32,
                             "effects": {"faults": [{"path": "qp32/seg_00001", "status": 404}]}}, "fatal", Path("."))
    sim = simulate(ladder, sc, "throughput")
    assert sim["error"].startswith("GOP 1: ") and "HTTP 404" in sim["error"] and sim["gops_played"] == 1
    with pytest.raises(PlaybackError, match=r"^GOP 1: .*HTTP 404"):
        emulate(sc, "throughput")


def test_faults_are_parsed_and_counted():
    faults = [{"path": "seg_00001", "status": 503, "times": 2}, {"path": "gop_", "status": 404}]
    fx = scenario({"faults": faults}).effects
    net = Network(fx)
    assert [net.fault("v/qp16/seg_00001.m4s") for _ in range(3)] == [503, 503, None]
    assert net.fault("v/keyframes/gop_00000.stgk") == 404 and net.fault("v/init.mp4") is None
    for bad in ([{"path": "x", "status": 200}], [{"path": "", "status": 404}], {"path": "x"},
                [{"path": "x", "status": 404, "times": 0}], [{"path": "x", "status": 404, "when": 1}]):
        with pytest.raises(StgsError, match="fault"):
            scenario({"faults": bad})


def test_the_clock_gives_the_first_gop_and_a_stalled_one_the_renderers_lead():
    from stgs.client.clock import PlaybackClock

    clock = PlaybackClock(segment_s=1.0, capacity_s=3.0, first_gop=0)
    assert clock.start(0, ready=0.4, arrived=0.0, lead=0.1) == 0.0 and clock.t0 == pytest.approx(0.5)
    assert clock.start_time(1, ready=1.2, arrived=1.5, lead=0.1) == pytest.approx(1.5)  # ready in time: when due
    assert clock.start(1, ready=1.2, arrived=1.5, lead=0.1) == 0.0 and clock.due(1) == pytest.approx(1.5)
    # GOP 2 is due at 2.5 and ready at 2.8: it starts 0.1 later, so the stall is 0.4
    assert clock.start(2, ready=2.8, arrived=2.5, lead=0.1) == pytest.approx(0.4)
    assert clock.due(2) == pytest.approx(2.9) and clock.stall_total == pytest.approx(0.4)

