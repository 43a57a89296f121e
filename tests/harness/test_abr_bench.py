"""bench/abr.py's own parts: its trace writers agree with the readers, its long ladder repeats the scene."""

from __future__ import annotations

import dataclasses
import statistics

import pytest

from bench.abr import SETS, generate, long_ladder, write
from stgs.harness.sim import simulate
from stgs.harness.trace import load_trace
from tests.harness.test_sim import EXAMPLE, hand_ladder, layered_ladder, layered_mpd, scenario


@pytest.mark.parametrize("fmt, suffix", [("mahimahi", "down"), ("pensieve", "log")])
def test_written_traces_read_back_at_their_rate(tmp_path, fmt, suffix):
    rates = [800.0, 2400.0, 0.0, 1200.0, 5000.0]  # kbit/s per second
    path = tmp_path / f"t.{suffix}"
    write(rates, fmt, path)
    trace = load_trace(path)  # the format is sniffed from the content
    delivered = [sum(k * 0.1 for t, k in zip(trace.times, trace.kbps, strict=True) if s <= t < s + 1)
                 for s in range(5)] if fmt == "mahimahi" else trace.kbps
    # Mahimahi quantises to whole 1500-byte packets (12 kbit): within one per second, plus the closing line's
    assert delivered == pytest.approx(rates, abs=24.0)
    assert trace.period == pytest.approx(5.0)


def test_generated_sets_are_reproducible_and_positive():
    for ts in SETS:
        a, b = generate(ts, 3), generate(ts, 3)
        assert a == b and min(a) >= 0 and statistics.mean(a) > 0


def test_long_ladder_repeats_gops_and_drops_rungs():
    base = hand_ladder(gops=2, media=(1, 2, 3, 4, 5))
    base.media_bytes = {r: [m, m * 10] for r, m in zip(base.media_bytes, (1, 2, 3, 4, 5), strict=True)}
    long = long_ladder(base, EXAMPLE.decode(), 7, qps=(32, 28, 24))
    assert long.pres.num_gops == 7 and [r.qp for r in long.pres.ladder] == [32, 28, 24]
    assert long.media_bytes["qp32"] == [1, 10, 1, 10, 1, 10, 1]
    assert set(long.media_bytes) == {"qp32", "qp28", "qp24"}


def test_the_long_ladder_keeps_the_static_layer_and_it_is_the_first_throughput_sample():
    base = layered_ladder(static=250_000, gops=2)
    long = long_ladder(base, layered_mpd(2).decode(), 6)
    assert long.static_bytes == 250_000 and long.pres.static is not None
    log = simulate(long, scenario({"bandwidth": {"kbps": 500}}), "throughput")
    first = log["gops"][0]
    assert first["requests"][0] == {"kind": "static", "rep": "static", "outcome": "250000 bytes"}
    # GOP 0's decision is made on the static layer's transfer: 2 Mbit at 500 kbit/s, not a 0-byte sample
    assert "estimate 500 kbit/s" in first["decisions"][0]["reason"]
    with pytest.raises(ValueError, match="static_bytes"):
        dataclasses.replace(long, static_bytes=0)
