"""Benchmarks, accuracy vs time (not installed): `stgs bench SUITE` from a source checkout runs bench/SUITE.py;
the A/B scripts run as `python -m bench.NAME` from the repository root. Results: docs/BENCHMARKS.md."""


def ms_cell(value: float) -> str:
    """A table cell in milliseconds: whole numbers from 100 ms, three significant digits below, so a fast step on a
    small test scene never reads as 0."""
    return f"{value:.0f}" if value >= 100 else f"{value:.3g}"
