"""bench/streaming/abr.py's own parts: its trace writers agree with the readers, its long ladder repeats the scene,
recorded trace folders and the paired intervals of `stgs bench abr`."""

from __future__ import annotations

import dataclasses
import math
import statistics
from pathlib import Path

import pytest
import scipy.stats

from bench.streaming.abr import SETS, generate, long_ladder, paired_ci, recorded_sets, write
from stgs.errors import StgsError
from stgs.harness.sim import simulate
from stgs.harness.trace import load_trace, load_trace_folder
from tests.conftest import run_stgs as stgs
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


def test_a_folder_is_a_recorded_trace_set_in_any_of_the_public_formats(tmp_path):
    write([800.0, 2400.0], "mahimahi", tmp_path / "a.down")
    write([1000.0, 3000.0], "pensieve", tmp_path / "b.log")
    write([500.0, 700.0], "pensieve", tmp_path / "d_fcc_http---www.example.com_0")  # recorded sets' own naming
    (tmp_path / "c.json").write_text('[{"duration_ms": 2000, "bandwidth_kbps": 600, "latency_ms": 30}]')
    (tmp_path / ".notes").write_text("not a trace")  # hidden files are skipped
    traces = load_trace_folder(tmp_path)
    assert [Path(t.source).name for t in traces] == ["a.down", "b.log", "c.json", "d_fcc_http---www.example.com_0"]
    assert [t.mean_kbps() for t in traces] == pytest.approx([1600.0, 2000.0, 600.0, 600.0], abs=12.0)
    # each set is scaled by one constant: its median trace's mean becomes the top rung
    scaled = recorded_sets([tmp_path], 40.0, 3200.0)[0]
    median = statistics.median(t.mean_kbps() for t in traces)
    assert statistics.median(t.mean_kbps() for t in scaled.traces) == pytest.approx(3200.0)
    assert scaled.traces[2].kbps == pytest.approx([600.0 * 3200.0 / median])
    assert recorded_sets([tmp_path], 40.0, None)[0].traces[1].kbps == traces[1].kbps
    (tmp_path / "e.log").write_text("0 1.0 7\n")
    with pytest.raises(StgsError, match=r"e\.log: malformed pensieve trace"):
        load_trace_folder(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(StgsError, match="no trace files"):
        load_trace_folder(tmp_path / "empty")


def test_the_paired_interval_is_the_paired_t_tests():
    a, b = [1.0, 2.5, 3.0, 4.2, 2.2], [0.8, 2.0, 3.1, 3.5, 2.0]
    mean, half = paired_ci(a, b)
    low, high = scipy.stats.ttest_rel(a, b).confidence_interval(0.95)
    assert (mean - half, mean + half) == pytest.approx((low, high))
    assert paired_ci([1.0], [0.5]) == (0.5, math.inf)


def test_stgs_bench_abr_plays_recorded_trace_folders(packed, tmp_path):
    lte, dsl = tmp_path / "lte", tmp_path / "dsl"
    lte.mkdir(), dsl.mkdir()
    for i, rates in enumerate(([400.0, 4000.0] * 5, [3000.0, 200.0, 2500.0] * 4)):
        write(rates, "mahimahi", lte / f"{i}.down")
        write([r * 2 for r in rates], "pensieve", dsl / f"{i}.log")
    out = stgs("bench", "abr", "--dash", str(packed), "--traces", f"{lte},{dsl}", "--latency-ms", "30")
    assert out.returncode == 0, out.stderr
    for name in ("lte", "dsl"):
        for buffer in (6, 25):
            assert f"**{name}, ladder QP 16-32, buffer {buffer} s** (2 recorded traces from" in out.stdout
    rows = [line.split(" | ") for line in out.stdout.splitlines() if line.startswith("| mpc |")]
    assert len(rows) == 4 and all("±" in row[9] for row in rows)
    bad = stgs("bench", "abr", "--dash", str(packed), "--traces", str(tmp_path / "missing"))
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "not a folder" in bad.stderr
    (lte / "2.down").write_text("0\nten\n")
    bad = stgs("bench", "abr", "--dash", str(packed), "--traces", str(lte))
    assert bad.returncode != 0 and "2.down: malformed" in bad.stderr and "Traceback" not in bad.stderr
