"""ABR rules against hand-computed decisions (dash.js-style unit tests with a mocked player state)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from stgs.client.abr import (
    AbandonRule,
    AbrSettings,
    AbrState,
    BolaERule,
    BolaRule,
    Decision,
    DynamicRule,
    FixedRule,
    InFlight,
    InsufficientBufferRule,
    MpcRule,
    ThroughputRule,
    ThroughputSample,
    UpcomingGOP,
    abandon_target,
    ewma_kbps,
    throughput_kbps,
)
from stgs.client.abr.predict import harmonic_kbps, predict_kbps, relative_error
from stgs.client.abr.state import MPC_PREDICTORS
from stgs.errors import FieldError

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


FIT_ONLY = AbrSettings(switch_up_headroom=0.0)
"""The throughput rule's fit alone (its start-up headroom has a test of its own)."""


def test_throughput_drop_moves_down_on_the_next_gop():
    rule = ThroughputRule(FIT_ONLY)
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
    assert ThroughputRule(FIT_ONLY).choose(state(samples=samples, keyframe_bits=650_000)).index == 1
    assert ThroughputRule(FIT_ONLY).choose(state(samples=samples, keyframe_bits=650_000,
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
    rule = DynamicRule()  # BOLA-E from 0.6 * 4 = 2.4 s, back to throughput below 0.3 * 4 = 1.2 s
    slow = kbps_samples((150, 4))  # throughput alone would pick the lowest rung
    assert rule.choose(state(buffer_s=2.0, samples=slow)).rule == "throughput" and not rule.using_bola
    assert rule.choose(state(buffer_s=4.0, samples=slow)).rule == "bola-e" and rule.using_bola
    rule.choose(state(buffer_s=1.5, samples=slow))
    assert rule.using_bola  # between the thresholds: keeps BOLA-E
    assert rule.choose(state(buffer_s=1.0, samples=slow)).rule == "throughput" and not rule.using_bola


def test_fixed_rule_ignores_everything():
    assert FixedRule(1).choose(state(buffer_s=0.0, samples=kbps_samples((1, 10)))).index == 1


def test_abandon_only_when_the_download_would_outlast_the_buffer_and_a_gop():
    settings = AbrSettings()
    sizes = [400_000.0, 800_000.0, 8_000_000.0]  # bits; the flight is the top rung's 1 MB

    def verdict(received=100_000, total=1_000_000, elapsed=1.0, ttfb=0.0, buffer=2.0, segment=1.0, rung=2):
        return abandon_target(InFlight(rung, received, total, elapsed, ttfb), sizes, buffer, segment, settings)

    # 100 kB in 1 s (800 kbit/s): 9 s to go > buffer 2 s; rung 1 (0.1 MB, 1 s) is not sustainable (> 0.9 s)
    assert verdict() == (0, pytest.approx(9.0), pytest.approx(0.5))
    assert verdict(buffer=10.0) is None  # the buffer outlasts it
    assert verdict(elapsed=0.1) is None  # too early to judge
    assert verdict(total=None) is None  # size unknown
    assert verdict(received=900_000, total=1_000_000) is None  # 0.11 s left: within the buffer
    assert verdict(segment=20.0) is None  # the whole transfer (10 s) keeps up with a 20-s GOP
    assert verdict(rung=0) is None  # nothing lower to fall to


def test_abandon_measures_the_body_not_the_round_trip():
    """A high-latency link: 32 kB of 100 kB arrive in 0.2 s after a 0.2-s round trip. Measured from the request
    (the old rule) that is 80 kB/s, 0.85 s to go at start-up (buffer 0): dropped. From the first byte it is
    160 kB/s, 0.425 s to go, 0.825 s in all: the download keeps up with a 1-s GOP and goes on."""
    settings = AbrSettings()
    sizes = [100_000.0, 400_000.0, 800_000.0]
    flight = InFlight(2, 32_000, 100_000, 0.4, 0.2)
    assert abandon_target(flight, sizes, 0.0, 1.0, settings) is None
    # and where the body itself is slow, it is dropped
    slow = InFlight(2, 16_000, 100_000, 1.2, 0.2)  # 16 kB/s: 5.25 s to go
    assert abandon_target(slow, sizes, 0.0, 1.0, settings)[0] == 0


def test_abandon_restarts_at_a_sustainable_rung_not_always_the_lowest():
    settings = AbrSettings()
    sizes = [100_000.0, 400_000.0, 800_000.0, 16_000_000.0]  # bits
    # 1 Mbit/s observed on the top rung's 2 MB: 15.8 s to go; rung 2 (0.8 Mbit) takes 0.05 + 0.8 s <= 0.9 s
    flight = InFlight(3, 25_000, 2_000_000, 0.25, 0.05)
    target, remaining, restart = abandon_target(flight, sizes, 1.0, 1.0, settings)
    assert target == 2 and restart == pytest.approx(0.85) and remaining == pytest.approx(15.8)


def test_the_throughput_rule_moves_up_only_with_headroom_and_down_at_once():
    samples = kbps_samples((1000, 1))  # 900 kbit/s to spend; rung 2 (100 + 400) needs 500, rung 1 300
    tight = state(samples=samples, keyframe_bits=450_000)  # rung 2 needs 850: fits, with 5.6 % to spare
    assert ThroughputRule(FIT_ONLY).choose(tight).index == 2
    from_below = ThroughputRule().choose(AbrState(**{**tight.__dict__, "current": 1}))
    assert from_below.index == 1 and "up needs 0.1 of the budget to spare" in from_below.reason
    assert ThroughputRule().choose(AbrState(**{**tight.__dict__, "current": 2})).index == 2  # held, no margin down
    too_big = AbrState(**{**tight.__dict__, "current": 2, "keyframe_bits": 550_000})  # 950 > 900: down at once
    assert ThroughputRule().choose(too_big).index == 1


def test_decisions_carry_the_rule_and_the_numbers_it_used():
    fast = kbps_samples((1000, 1))
    d = ThroughputRule().choose(state(samples=fast, keyframe_bits=300_000))
    assert d == Decision(2, "throughput", d.reason)
    assert d.reason == "estimate 1000 kbit/s x 0.9 = budget 900 kbit/s; rung 2 sustains 700"
    assert ThroughputRule().choose(state()).reason == "no throughput sample yet: lowest rung"
    dyn = DynamicRule().choose(state(buffer_s=4.0, samples=kbps_samples((150, 4))))
    assert dyn.rule == "bola-e" and dyn.reason.startswith("dynamic: buffer 4.00 s") and "placeholder" in dyn.reason
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
    assert d.reason == "9.00 s left at 800 kbit/s > buffer 2.00 s and one GOP; rung 0 takes 0.50 s"


def test_throughput_is_measured_on_the_body_and_round_trips_are_budgeted():
    # 125 kB in 1.1 s of which 0.1 s was the round trip: 1000 kbit/s of bandwidth, not 909
    sample = ThroughputSample(125_000, 1.1, 0.1)
    assert sample.kbps == pytest.approx(1000.0)
    assert ewma_kbps([sample], 3.0) == pytest.approx(1000.0)
    rule = ThroughputRule(FIT_ONLY)
    # 900 kbit/s to spend: keyframe 300 kbit + rung 2 (400 kbit) = 700 kbit fits 1 s; after one 0.1-s round trip
    # 0.9 s x 900 = 810 kbit still does; after two 0.15-s ones (0.7 s x 900 = 630 kbit) only rung 1 (500) does
    assert rule.choose(state(samples=[sample], keyframe_bits=300_000)).index == 2
    slow_rtt = [ThroughputSample(125_000, 1.15, 0.15)]
    high = AbrState(LADDER, 1.0, 0.0, 4.0, slow_rtt, 300_000, round_trips=2)
    decision = rule.choose(high)
    assert decision.index == 1 and "300 ms of round trips" in decision.reason
    assert rule.choose(AbrState(LADDER, 1.0, 0.0, 4.0, slow_rtt, 300_000, round_trips=1)).index == 2


def test_bola_e_starts_where_the_throughput_is_then_follows_its_placeholder():
    rule = BolaERule()
    fast = kbps_samples((2_000, 4))
    first = rule.choose(state(buffer_s=0.0, samples=fast))
    # start-up: the throughput rule's rung (top), and a placeholder that makes BOLA agree at this buffer
    assert first.index == 2 and "start-up" in first.reason
    low, _ = rule.bola.thresholds(state(samples=fast), 2)
    assert rule.placeholder_s == pytest.approx(low) and low > 0
    assert BolaRule().choose(state(buffer_s=rule.placeholder_s, samples=fast)).index == 2
    # steady (the buffer has held a GOP): the placeholder carries BOLA where the real buffer alone would not
    rule.steady = True
    steady = rule.choose(AbrState(LADDER, 1.0, 1.0, 4.0, fast, 100_000.0, waited_s=0.0))
    assert steady.index == 2 and BolaRule().choose(state(buffer_s=1.0, samples=fast)).index < 2
    # a stall (buffer empty while playing): back to start-up, placeholder gone
    rule.choose(AbrState(LADDER, 1.0, 0.0, 4.0, kbps_samples((150, 4)), 100_000.0))
    assert rule.placeholder_s == 0.0 and not rule.steady


def test_bola_e_holds_below_an_unsustainable_climb():
    """BOLA-O: BOLA alone would climb to the top on a full buffer; with throughput for rung 0 only and the last
    choice at 0 it stays at 0."""
    rule = BolaERule(steady=True, last=0)
    slow = kbps_samples((150, 4))
    decision = rule.choose(state(buffer_s=3.0, samples=slow))
    assert BolaRule().choose(state(buffer_s=3.0, samples=slow)).index == 2
    assert decision.index == 0 and "BOLA-O" in decision.reason


def test_insufficient_buffer_caps_what_cannot_arrive_in_time():
    rule = InsufficientBufferRule()
    fast = kbps_samples((1_000, 4))
    # 0.5 x 1.2 s = 0.6 s at 1000 kbit/s = 600 kbit: keyframe 100 + rung 2 (400) fits
    assert rule.choose(state(buffer_s=1.2, samples=fast)).index == 2
    # 0.5 x 0.5 s -> 250 kbit: keyframe 100 + rung 0 (100) only
    assert rule.choose(state(buffer_s=0.5, samples=fast)).index == 0
    assert rule.choose(state(buffer_s=0.5)) is None  # no sample: no opinion
    not_playing = AbrState(LADDER, 1.0, 0.0, 4.0, fast, 100_000.0, playing=False)
    assert rule.choose(not_playing) is None  # start-up is not a shortage
    dyn = DynamicRule().choose(state(buffer_s=0.5, samples=fast))
    assert dyn.index == 0 and dyn.rule == "insufficient-buffer" and "capped" in dyn.reason


def mpc_state(buffer_s, samples, upcoming, current=None, capacity=6.0) -> AbrState:
    return AbrState(LADDER, 1.0, buffer_s, capacity, samples, upcoming[0].keyframe_bits, upcoming[0].segment_bits,
                    current, upcoming=upcoming)


def test_mpc_plans_over_the_next_gops_exact_sizes():
    samples = [ThroughputSample(125_000, 1.0)] * 5  # 1000 kbit/s, steady (no prediction error)
    quiet = UpcomingGOP(100_000, [100_000, 200_000, 400_000])
    # the top rung fits every quiet GOP (500 kbit in 0.5 s): top
    assert MpcRule(AbrSettings(mpc_utility="bitrate")).choose(mpc_state(1.0, samples, [quiet] * 5)).index == 2
    # the GOPs after the next are huge at every rung: with 1 s of buffer the plan saves now to avoid the stall
    huge = UpcomingGOP(100_000, [1_500_000, 3_000_000, 6_000_000])
    ahead = MpcRule(AbrSettings(mpc_utility="bitrate")).choose(mpc_state(1.0, samples, [quiet, huge, huge]))
    assert ahead.index < 2
    # a rule that only sees the next GOP keeps the top rung; the throughput rule decides on the sustained sizes
    assert ThroughputRule(AbrSettings(sustained_gops=1)).choose(mpc_state(1.0, samples, [quiet, huge, huge])).index == 2
    assert ThroughputRule().choose(mpc_state(1.0, samples, [quiet, huge, huge])).index == 0


def test_mpc_maximises_rendered_quality_not_bits():
    samples = [ThroughputSample(125_000, 1.0)] * 5
    # rung 2 costs twice rung 1's bits but renders no better (a saturated ladder): PSNR utility keeps rung 1,
    # bit-rate utility takes rung 2
    flat = UpcomingGOP(100_000, [100_000, 200_000, 400_000], [30.0, 36.0, 36.0])
    assert MpcRule(AbrSettings(mpc_utility="psnr")).choose(mpc_state(3.0, samples, [flat] * 5, current=1)).index == 1
    assert MpcRule(AbrSettings(mpc_utility="bitrate")).choose(mpc_state(3.0, samples, [flat] * 5,
                                                                         current=1)).index == 2


def test_mpc_bounds_the_throughput_by_its_past_errors():
    rule = MpcRule(AbrSettings(mpc_predictor="harmonic"))
    steady = [ThroughputSample(125_000, 1.0)] * 3
    assert rule.predict_kbps(AbrState(LADDER, 1.0, 1.0, 6.0, steady)) == pytest.approx((1000.0, 1000.0))
    # the next sample came in at half the prediction: error 100 %, the robust estimate halves
    dropped = [*steady, ThroughputSample(62_500, 1.0)]
    harmonic, robust = rule.predict_kbps(AbrState(LADDER, 1.0, 1.0, 6.0, dropped))
    assert harmonic == pytest.approx(4 / (3 / 1000 + 1 / 500)) and robust == pytest.approx(harmonic / 2)
    assert MpcRule().choose(AbrState(LADDER, 1.0, 0.0, 6.0, [])).index == 0


HISTORIES = {
    "empty": [],
    "one sample": [700.0],
    "zero throughput": [0.0, 0.0, 0.0],
    "zero after steady": [1000.0] * 8 + [0.0],
    "huge": [1e300, 1e308, 5.0],
    "infinite": [math.inf, 1000.0],
    "long heavy tail": [10.0 ** (k % 7) for k in range(60)],
}


@pytest.mark.parametrize("predictor", MPC_PREDICTORS)
@pytest.mark.parametrize("history", list(HISTORIES))
def test_every_predictor_is_finite_and_non_negative_on_any_history(predictor, history):
    kbps = HISTORIES[history]
    settings = AbrSettings(mpc_predictor=predictor)
    errors = [relative_error(p, a) for p, a in zip([harmonic_kbps(kbps[:i]) for i in range(1, len(kbps))],
                                                   kbps[1:], strict=True)]
    assert all(math.isfinite(e) and e >= 0 for e in errors)
    value = predict_kbps(predictor, kbps, errors, settings)
    assert math.isfinite(value) and value >= 0
    assert (value == 0) == (not kbps)  # 0 only without a sample
    if len(set(kbps)) == 1 and kbps[0] > 0:  # a steady history predicts itself
        assert value == pytest.approx(kbps[0])


def test_the_lower_predictors_sit_below_a_bursty_historys_mean():
    bursty = [4000.0, 300.0, 5000.0, 250.0, 6000.0, 3500.0, 200.0, 4500.0] * 3
    mean = sum(bursty) / len(bursty)
    for predictor in ("quantile", "ewma-lower"):
        assert predict_kbps(predictor, bursty, [], AbrSettings()) < 0.5 * mean, predictor
    assert predict_kbps("quantile", bursty, [], AbrSettings(mpc_quantile=0.0)) == pytest.approx(200.0)
    # the long error bound keeps an outage's error for mpc_error_horizon GOPs, the short one for mpc_history
    errors = [3.0] + [0.0] * 10
    steady = [1000.0] * 11
    assert predict_kbps("harmonic", steady, errors, AbrSettings()) == pytest.approx(1000.0)
    assert predict_kbps("error-bound", steady, errors, AbrSettings()) == pytest.approx(250.0)
    with pytest.raises(FieldError, match="mpc_predictor"):
        AbrSettings(mpc_predictor="oracle")


def test_mpc_with_the_buffer_constraint_keeps_the_reservoir():
    samples = [ThroughputSample(125_000, 1.0)] * 5  # 1000 kbit/s, steady
    # over a one-GOP horizon: the top rung takes 3 s (4 s of buffer -> 2 s), the middle rung 0.6 s (-> 4.4 s).
    # Charged only for stalls, the plan takes the top rung; constrained to the 4-s reservoir, the middle one
    heavy = UpcomingGOP(100_000, [100_000, 500_000, 2_900_000], [30.0, 36.0, 52.0])
    one = AbrSettings(mpc_horizon=1, mpc_reservoir_weight=0.0, mpc_buffer_constraint=False, mpc_utility="psnr")
    assert MpcRule(one).choose(mpc_state(4.0, samples, [heavy], capacity=8.0)).index == 2
    kept = MpcRule(dataclasses.replace(one, mpc_buffer_constraint=True)).choose(
        mpc_state(4.0, samples, [heavy], capacity=8.0))
    assert kept.index == 1
    # below the reservoir no plan can reach it: the plans that keep the buffer where it stands are left
    low = MpcRule(AbrSettings(mpc_buffer_constraint=True)).choose(mpc_state(1.0, samples, [heavy] * 5, capacity=8.0))
    assert low.index <= 1


def test_upcoming_gop_from_stats_reads_bits_and_psnr_and_refuses_what_stats_does_not_say():
    reps = {"f30": {"bytes": 1000, "render_psnr": 30.5}, "f24": {"bytes": 4000, "render_psnr": 33.0}}
    stats = {"gops": [{"index": 0, "keyframe_bytes": 500, "representations": reps}]}
    gop = UpcomingGOP.from_stats(stats, 0, ["f30", "f24"])
    assert gop.keyframe_bits == 4000 and list(gop.segment_bits) == [8000, 32000] and list(gop.psnr) == [30.5, 33.0]
    assert UpcomingGOP.from_stats(stats, 1, ["f30"]) is None  # no such GOP
    assert UpcomingGOP.from_stats(stats, 0, ["f18"]) is None  # no such rung
    assert UpcomingGOP.from_stats({"gops": [{**stats["gops"][0], "index": 3}]}, 0, ["f30"]) is None
    zero = {"gops": [{"index": 0, "keyframe_bytes": 0, "representations": reps}]}
    assert UpcomingGOP.from_stats(zero, 0, ["f30"]) is None
    no_psnr = {"f30": {"bytes": 1000, "render_psnr": float("nan")}}
    partial = UpcomingGOP.from_stats({"gops": [{"index": 0, "keyframe_bytes": 500, "representations": no_psnr}]},
                                     0, ["f30"])
    assert partial is not None and partial.psnr is None
    assert UpcomingGOP.from_stats("not a document", 0, ["f30"]) is None
