"""Benchmarks, accuracy vs time (not installed): `stgs bench SUITE` from a source checkout runs bench/SUITE.py;
the A/B scripts run as `python -m bench.NAME` from the repository root. Results: docs/BENCHMARKS.md."""
