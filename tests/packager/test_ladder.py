"""The auto ladder's choice of rungs (stgs/packager/ladder.py) on measured-looking candidates."""

from __future__ import annotations

import itertools
import random

import pytest

from stgs.errors import FieldError
from stgs.packager.ladder import Candidate, LadderRules, allocation_saving, choose_rungs, upper_hull

RULES = LadderRules()


def kept(verdicts):
    return [v.rep_id for v in verdicts if v.kept]


def curve(points: list[tuple[int, float]]) -> list[Candidate]:
    return [Candidate(f"q{i}", b, p) for i, (b, p) in enumerate(points)]


def under(c: Candidate, a: Candidate, b: Candidate) -> bool:
    """Whether c lies strictly under the segment a-b (a.bytes <= c.bytes <= b.bytes)."""
    return (c.psnr - a.psnr) * (b.bytes - a.bytes) < (b.psnr - a.psnr) * (c.bytes - a.bytes) - 1e-9


def test_a_saturating_curve_keeps_a_spaced_ladder_with_its_top_where_gains_stop():
    # rate doubles per step; the gain shrinks and the last two steps buy under 0.05 dB
    cands = curve([(1000, 30.0), (2000, 33.0), (4000, 35.0), (8000, 36.0), (16000, 36.4), (32000, 36.44),
                   (64000, 36.46)])
    verdicts = choose_rungs(cands, RULES)
    assert kept(verdicts) == ["q0", "q1", "q2", "q3", "q4"]
    reasons = {v.rep_id: v.reason for v in verdicts}
    assert "above the top" in reasons["q5"] and "above the top" in reasons["q6"]
    assert reasons["q0"].startswith("the floor") and reasons["q4"].startswith("the top")


def test_rungs_closer_than_the_ratio_or_the_gain_are_dropped():
    cands = curve([(1000, 30.0), (1200, 31.0), (1600, 32.0), (2400, 33.0), (2500, 33.05), (5000, 34.0)])
    verdicts = choose_rungs(cands, RULES)
    chosen = [c for c in cands if c.rep_id in kept(verdicts)]
    assert chosen[0].rep_id == "q0" and chosen[-1].rep_id == "q5"
    for below, above in itertools.pairwise(chosen):
        assert above.bytes >= RULES.min_ratio * below.bytes and above.psnr - below.psnr >= RULES.min_gain_db
    reasons = {v.rep_id: v.reason for v in verdicts}
    assert "costs only" in reasons["q3"] and "costs only" in reasons["q1"]


@pytest.mark.parametrize("seed", range(20))
def test_chosen_rungs_are_monotone_and_none_lies_under_the_hull(seed):
    rng = random.Random(seed)
    points = [(rng.randint(1_000, 1_000_000), rng.uniform(20.0, 50.0)) for _ in range(rng.randint(1, 12))]
    cands = curve(points)
    chosen = [c for c in sorted(cands, key=lambda c: c.bytes) if c.rep_id in kept(choose_rungs(cands, RULES))]
    assert chosen, "a ladder has at least one rung"
    for below, above in itertools.pairwise(chosen):
        assert above.bytes > below.bytes and above.psnr > below.psnr
    for c in chosen:  # no candidate pair spans a chosen rung from above
        assert not any(under(c, a, b) for a in cands for b in cands if a.bytes <= c.bytes <= b.bytes and a is not b)
    assert len({c.rep_id for c in upper_hull(cands)} & {c.rep_id for c in chosen}) == len(chosen)


def test_one_candidate_and_a_flat_curve_each_give_one_rung():
    assert kept(choose_rungs(curve([(5000, 40.0)]), RULES)) == ["q0"]
    flat = curve([(1000 * 2 ** i, 99.0) for i in range(6)])  # every QP renders the same
    verdicts = choose_rungs(flat, RULES)
    assert kept(verdicts) == ["q0"] and all("under the rate-quality hull" in v.reason for v in verdicts[1:])
    assert choose_rungs([], RULES) == []


def test_a_top_too_close_to_the_rung_below_replaces_it():
    # going down from the top q3, q2 is dropped (q3 costs only 1.25x its bytes) and q1 kept (q3 costs 2.5x its bytes)
    cands = curve([(1000, 30.0), (2000, 32.0), (4000, 34.0), (5000, 34.6)])
    assert kept(choose_rungs(cands, RULES)) == ["q0", "q1", "q3"]


def test_the_floor_replaces_the_lowest_rung_it_sits_too_close_to():
    cands = curve([(1000, 30.0), (1300, 31.0), (3000, 33.0), (6000, 34.0)])
    verdicts = choose_rungs(cands, RULES)
    assert kept(verdicts) == ["q0", "q2", "q3"]


def test_rules_are_checked():
    with pytest.raises(FieldError, match="min_ratio"):
        LadderRules(min_ratio=0.5).validate()
    with pytest.raises(FieldError, match="top_gain_db"):
        LadderRules(top_gain_db=float("nan")).validate()


def test_allocation_saving_is_zero_for_identical_gops_and_positive_where_they_differ():
    same = curve([(1000, 30.0), (2000, 33.0), (4000, 35.0)])
    rungs = [Candidate(c.rep_id, 2 * c.bytes, c.psnr) for c in same]
    assert allocation_saving([same, same], rungs) == pytest.approx(0.0, abs=1e-12)
    easy = curve([(1000, 40.0), (2000, 40.5), (4000, 40.7)])  # more bytes buy little here
    hard = curve([(1000, 30.0), (2000, 34.0), (4000, 37.0)])  # and much here
    rungs = [Candidate(e.rep_id, e.bytes + h.bytes, (e.psnr + h.psnr) / 2) for e, h in zip(easy, hard, strict=True)]
    assert 0.0 < allocation_saving([easy, hard], rungs) < 0.5


class _Features:
    def __init__(self, rep_id: str):
        self.rep_id = rep_id


def _pairs(*ids: str) -> dict:
    """pair id -> (feature records stand-in, keyframe Representation), as Packer.choose_ladder builds them."""
    out = {}
    for pid in ids:
        features, _, keyframe = pid.partition("+")
        out[pid] = (_Features(features), keyframe or "keyframes")
    return out


def test_pairs_put_the_lossless_keyframe_on_top_where_it_renders_as_well_and_keep_one_rung_per_feature_point():
    from stgs.packager.ladder import Verdict
    from stgs.packager.packer import pair_rungs

    pairs = _pairs("qp40+keyframes-coarse", "qp36+keyframes-coarse", "qp36+keyframes-fine", "qp24+keyframes-fine",
                   "qp24")
    verdicts = [Verdict(pid, True, "kept") for pid in pairs]  # cheapest first, as choose_rungs lists them
    quality = {"qp40+keyframes-coarse": 30.0, "qp36+keyframes-coarse": 31.0, "qp36+keyframes-fine": 32.0,
               "qp24+keyframes-fine": 35.0, "qp24": 35.2}
    verdicts[-1] = Verdict("qp24", False, "above the top")
    out = {v.rep_id: v for v in pair_rungs(verdicts, pairs, quality)}
    assert [pid for pid, v in out.items() if v.kept] == ["qp40+keyframes-coarse", "qp36+keyframes-fine", "qp24"]
    assert "lossless keyframe" in out["qp24+keyframes-fine"].reason
    assert "already" in out["qp36+keyframes-coarse"].reason
    # a lossless pair that renders worse than the top pair (the demo scene's rotation grid) leaves the top as it is
    out = {v.rep_id: v for v in pair_rungs(verdicts, pairs, quality | {"qp24": 34.0})}
    assert out["qp24+keyframes-fine"].kept and not out["qp24"].kept
