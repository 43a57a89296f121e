"""bench.training.layered_stream's bytes at equal rendered PSNR: a format-2 ladder read at a format-1 rung's PSNR, with
log KB linear in PSNR between rungs (worked by hand here) and no extrapolation."""

from __future__ import annotations

import math

import pytest

from bench.training.layered_stream import equal_psnr_rows, kb_at_psnr


def test_between_two_rungs_log_kb_is_linear_in_psnr():
    ladder = [(44.0, 40.0), (40.0, 10.0)]  # unsorted on purpose
    assert kb_at_psnr(ladder, 42.0) == pytest.approx(20.0)  # halfway in PSNR: the geometric mean
    assert kb_at_psnr(ladder, 41.0) == pytest.approx(10.0 * math.sqrt(2.0))
    assert kb_at_psnr(ladder, 40.0) == pytest.approx(10.0)
    assert kb_at_psnr(ladder, 44.0) == pytest.approx(40.0)


def test_outside_the_ladder_there_is_no_value():
    ladder = [(40.0, 10.0), (44.0, 40.0), (46.0, 80.0)]
    assert kb_at_psnr(ladder, 39.99) is None
    assert kb_at_psnr(ladder, 46.01) is None
    assert kb_at_psnr([], 42.0) is None
    assert kb_at_psnr(ladder, 45.0) == pytest.approx(40.0 * math.sqrt(2.0))  # the upper segment


def test_rows_follow_the_reference_ladder_in_qp_order():
    reference = {"r32": {"qp": 32, "render_psnr": 39.0, "kb": 8.0},
                 "r16": {"qp": 16, "render_psnr": 42.0, "kb": 40.0}}
    candidate = {"a": {"qp": 24, "render_psnr": 40.0, "kb": 10.0}, "b": {"qp": 16, "render_psnr": 44.0, "kb": 40.0}}
    rows = equal_psnr_rows(reference, candidate, "kb")
    assert [r["qp"] for r in rows] == [16, 32]
    assert rows[0]["candidate_kb"] == pytest.approx(20.0)
    assert rows[0]["ratio"] == pytest.approx(0.5)
    assert rows[1]["candidate_kb"] is None and rows[1]["ratio"] is None  # 39 dB: below the candidate's ladder
