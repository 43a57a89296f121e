"""bench.synth's smoothness table (`stgs bench synth`) on a tiny scene: one row per (smoothness, QP), with positive
rates, a rendered PSNR and decode times."""

from __future__ import annotations

from bench.training.synth import smoothness_table
from stgs.synth import SynthConfig


def test_bench_synth_smoothness_table(capsys):
    tiny = SynthConfig(grid_side=8, num_gops=1, gop_size=4, width=32, height=24, num_cameras=1, fit_steps=10)
    assert smoothness_table(tiny, [0.3], [32]) == 0
    rows = [line.split("|")[1:-1] for line in capsys.readouterr().out.splitlines() if line.startswith("| 0.3 |")]
    assert len(rows) == 1
    mbits, rendered, decode_ms = (float(v) for v in rows[0][3].split(","))
    assert mbits > 0 and 0 < rendered <= 99 and decode_ms > 0
