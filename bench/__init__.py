"""Benchmarks, accuracy vs time (not installed): `stgs bench SUITE` from a source checkout runs bench/SUITE.py;
the A/B scripts run as `python -m bench.NAME` from the repository root. Results: docs/BENCHMARKS.md."""

import argparse
import platform
import subprocess
from collections.abc import Callable


def ms_cell(value: float) -> str:
    """A table cell in milliseconds: whole numbers from 100 ms, three significant digits below, so a fast step on a
    small test scene never reads as 0."""
    return f"{value:.0f}" if value >= 100 else f"{value:.3g}"


def capacity_parser(doc: str, capacities: str) -> argparse.ArgumentParser:
    """The arguments of an A/B over GOP models of several Gaussian counts: --capacities and --steps."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--capacities", default=capacities, help="comma-separated Gaussian counts N")
    parser.add_argument("--steps", type=int, default=30)
    return parser


def torch_table_header(suite: str) -> str:
    """The comment a printed table starts with: the suite, the CPU, torch's threads and the commit measured."""
    import torch

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    return (f"<!-- python -m bench.{suite}, {platform.processor() or platform.machine()}, "
            f"torch threads {torch.get_num_threads()}, commit {commit} -->")


def print_capacity_table(args: argparse.Namespace, header: str, measure: Callable[[int, int], str]) -> int:
    """Print a Markdown table: `header` ("| a | b |"), then measure(N, steps) for each of --capacities."""
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for n in args.capacities.split(","):
        print(measure(int(n), args.steps), flush=True)
    return 0
