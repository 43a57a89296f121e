"""ABR rules against hand-computed decisions (dash.js-style unit tests with a mocked player state)."""

from __future__ import annotations

import math

import pytest

from stgs.client.abr import (
    AbandonRule,
    AbrSettings,
    AbrState,
    BolaRule,
    Decision,
    DynamicRule,
    FixedRule,
    InFlight,
    ThroughputRule,
    ThroughputSample,
    ewma_kbps,
    should_abandon,
    throughput_kbps,
)

LADDER = [100_000, 200_000, 400_000]  # bit/s, one-second GOPs


def state(buffer_s=0.0, samples=(), keyframe_bits=100_000.0, segment_bits=None, capacity=4.0) -> AbrState:
    return AbrState(LADDER, 1.0, buffer_s, capacity, list(samples), keyframe_bits, segment_bits)


def kbps_samples(*pairs) -> list[ThroughputSample]:
    """(kbit/s, seconds) -> samples."""
    return [ThroughputSample(round(kbps * 1e3 / 8 * s), s) for kbps, s in pairs]


def test_ewma_of_a_constant_is_that_constant():
    assert ewma_kbps(kbps_samples((1000, 1), (1000, 2), (1000, 0.5)), 3.0) == pytest.approx(1000, rel=1e-9)
    assert ewma_kbps([], 3.0) is None


def test_ewma_by_hand():
    # fast (3 s): a1 = 0.5^(1/3), e = (1 - a1) * 1000 = 206.30; a2 = 0.5^(3/3), e = 0.5 * 206.30 + 0.5 * 200
    # = 203.15; zero-bias correction / (1 - 0.5^(4/3)) = / 0.60315 -> 336.81
    # slow (8 s): e1 = (1 - 0.5^(1/8)) * 1000 = 83.00; e2 = 0.77111 * 83.00 + 0.22889 * 200 = 109.78;
    # / (1 - 0.5^(4/8)) = / 0.29289 -> 374.80. The rule uses the lower: 336.81.
    samples = kbps_samples((1000, 1), (200, 3))
    assert ewma_kbps(samples, 3.0) == pytest.approx(336.81, abs=0.02)
    assert ewma_kbps(samples, 8.0) == pytest.approx(374.80, abs=0.02)
    assert throughput_kbps(samples, AbrSettings()) == pytest.approx(336.81, abs=0.02)


def test_throughput_rule_starts_low_then_spends_the_safe_budget():
    rule = ThroughputRule()
    assert rule.choose(state()).index == 0  # no history yet
    # 1000 kbit/s * 0.9 - 100 kbit/s keyframe = 800 kbit/s >= 400 kbit/s: the top rung
    assert rule.choose(state(samples=kbps_samples((1000, 1)))).index == 2


def test_throughput_drop_moves_down_on_the_next_gop():
    rule = ThroughputRule()
    # estimate 336.81 kbit/s (test_ewma_by_hand): budget 0.9 * 336.81 - 100 = 203.1 kbit/s -> 200k rung
    assert rule.choose(state(samples=kbps_samples((1000, 1), (200, 3)))).index == 1
    # a deeper drop: nothing fits, the lowest rung
    assert rule.choose(state(samples=kbps_samples((1000, 1), (50, 6)))).index == 0


def test_throughput_rule_budgets_the_keyframe():
    rule = ThroughputRule()
    fast = kbps_samples((1000, 1))
    assert rule.choose(state(samples=fast, keyframe_bits=300_000)).index == 2  # 900 - 300 = 600 >= 400
    assert rule.choose(state(samples=fast, keyframe_bits=600_000)).index == 1  # 900 - 600 = 300: 200 fits, 400 not
    assert rule.choose(state(samples=fast, keyframe_bits=850_000)).index == 0  # 50 left


def test_throughput_rule_uses_the_next_gops_actual_sizes():
    # The top rung's next segment is small (a quiet GOP): it fits a 250 kbit/s budget although @bandwidth does not.
    samples = kbps_samples((1000, 1))
    assert ThroughputRule().choose(state(samples=samples, keyframe_bits=650_000)).index == 1
    assert ThroughputRule().choose(state(samples=samples, keyframe_bits=650_000,
                                         segment_bits=[50_000, 240_000, 245_000])).index == 2


def test_bola_by_hand():
    rule = BolaRule()
    s = state(buffer_s=0.0)
    sizes, utilities, v, gp = rule.parameters(s)
    # sizes = keyframe + features = 200k, 300k, 500k bits; v_m = ln(size/200k) + 1
    assert sizes == [200_000, 300_000, 500_000]
    assert utilities == pytest.approx([1.0, 1 + math.log(1.5), 1 + math.log(2.5)])
    # min buffer = one segment (1 s), target = capacity - one segment = 3 s: gp = (v_max - 1) / (3/1 - 1)
    assert gp == pytest.approx(math.log(2.5) / 2)
    assert v == pytest.approx(1 / gp)


def test_bola_climbs_as_the_buffer_fills():
    rule = BolaRule()
    choices = [rule.choose(state(buffer_s=b)).index for b in (0.0, 1.0, 2.0, 3.0, 4.0)]
    assert choices[0] == 0 and choices[-1] == 2  # empty buffer: lowest; full buffer: top
    assert choices == sorted(choices)


@pytest.mark.parametrize("capacity", [6.0, 25.0])
def test_bola_reaches_the_top_rung_at_the_highest_buffer_a_decision_is_made_at(capacity):
    """The fetcher decides only when a whole GOP fits (buffer <= capacity - T): BOLA's top rung must be
    reachable there (with the whole capacity as its target it never was: 5.67 s needed at 6 s, 23.08 at 25)."""
    segment_s = 2.0
    ladder = [1_330_000, 2_000_000, 3_000_000, 4_500_000, 7_600_000]  # 2.65-8.9 Mbit/s with the keyframe
    s = AbrState(ladder, segment_s, capacity - segment_s, capacity, [], 1_300_000 * segment_s)
    assert BolaRule().choose(s).index == len(ladder) - 1
    low = AbrState(ladder, segment_s, segment_s / 2, capacity, [], 1_300_000 * segment_s)
    assert BolaRule().choose(low).index == 0


def test_dynamic_takes_bola_only_when_it_is_at_least_the_throughput_choice():
    rule = DynamicRule()  # BOLA band from 0.6 * 4 = 2.4 s down to 0.3 * 4 = 1.2 s
    fast = kbps_samples((2_000, 4))  # throughput alone picks the top rung
    rule.choose(state(buffer_s=2.5, samples=fast))
    assert rule.using_bola
    assert BolaRule().choose(state(buffer_s=1.5, samples=fast)).index == 1  # BOLA alone would pick less here
    decision = rule.choose(state(buffer_s=1.5, samples=fast))
    assert rule.using_bola and decision.index == 2 and decision.rule == "throughput"
    assert "below throughput's" in decision.reason


def test_dynamic_switches_with_hysteresis():
    rule = DynamicRule()  # BOLA from 0.6 * 4 = 2.4 s, back to throughput below 0.3 * 4 = 1.2 s
    slow = kbps_samples((150, 4))  # throughput alone would pick the lowest rung
    assert rule.choose(state(buffer_s=2.0, samples=slow)).index == 0 and not rule.using_bola
    assert rule.choose(state(buffer_s=4.0, samples=slow)).index == 2 and rule.using_bola
    rule.choose(state(buffer_s=1.5, samples=slow))
    assert rule.using_bola  # between the thresholds: keeps BOLA
    assert rule.choose(state(buffer_s=1.0, samples=slow)).index == 0 and not rule.using_bola


def test_fixed_rule_ignores_everything():
    assert FixedRule(1).choose(state(buffer_s=0.0, samples=kbps_samples((1, 10)))).index == 1


def test_abandon_only_when_the_download_would_outlast_the_buffer():
    settings = AbrSettings()
    # 100 kB of 1 MB in 1 s (100 kB/s): 9 s to go, buffer 2 s -> abandon (the lowest rung, 50 kB, takes 0.5 s)
    assert should_abandon(100_000, 1_000_000, 1.0, 2.0, 50_000, settings)
    assert not should_abandon(100_000, 1_000_000, 1.0, 10.0, 50_000, settings)  # the buffer outlasts it
    assert not should_abandon(100_000, 1_000_000, 0.1, 2.0, 50_000, settings)  # too early to judge
    assert not should_abandon(100_000, None, 1.0, 2.0, 50_000, settings)  # size unknown
    assert not should_abandon(100_000, 1_000_000, 1.0, 2.0, 950_000, settings)  # restarting is no faster


def test_decisions_carry_the_rule_and_the_numbers_it_used():
    fast = kbps_samples((1000, 1))
    d = ThroughputRule().choose(state(samples=fast, keyframe_bits=300_000))
    assert d == Decision(2, "throughput", d.reason)
    assert "estimate 1000 kbit/s" in d.reason and "keyframe 300" in d.reason and "budget 600" in d.reason
    assert ThroughputRule().choose(state()).reason == "no throughput sample yet: lowest rung"
    dyn = DynamicRule().choose(state(buffer_s=4.0, samples=kbps_samples((150, 4))))
    assert dyn.rule == "bola" and dyn.reason.startswith("dynamic: buffer 4.00 s") and "V " in dyn.reason
    assert FixedRule(1).choose(state()).to_json() == {"index": 1, "rule": "fixed", "reason": "pinned rung 1"}


def test_abandonment_is_a_rule_with_a_reason():
    rule = AbandonRule()
    lowest = [400_000.0, 800_000.0, 8_000_000.0]  # bits: the lowest rung is 50 kB
    judged = state(buffer_s=2.0, segment_bits=lowest)
    assert rule.choose(judged) is None  # nothing in flight
    keep = AbrState(**{**judged.__dict__, "in_flight": InFlight(2, 100_000, 1_000_000, 0.1)})
    assert rule.choose(keep) is None  # too early to judge
    drop = AbrState(**{**judged.__dict__, "in_flight": InFlight(2, 100_000, 1_000_000, 1.0)})
    d = rule.choose(drop)
    assert d.index == 0 and d.rule == "abandon"
    assert d.reason == "9.00 s left at 800 kbit/s > buffer 2.00 s; the lowest rung takes 0.50 s"
    lowest_in_flight = AbrState(**{**judged.__dict__, "in_flight": InFlight(0, 100_000, 1_000_000, 1.0)})
    assert rule.choose(lowest_in_flight) is None  # nothing lower to fall to
