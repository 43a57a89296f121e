"""Benchmarks, accuracy vs time (not installed), grouped by the question they answer (bench/README.md): `stgs
bench SUITE` from a source checkout runs one of them (stgs.cli.study.SUITES), and every script runs as
`python -m bench.GROUP.NAME` from the repository root. Results: docs/BENCHMARKS.md."""

import argparse
import json
import os
import platform
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path


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


def run_tree(tree: Path, child: str, args: list[str]) -> dict:
    """Run the Python source `child` with `args` against the source tree `tree` (first on PYTHONPATH, so its own
    sources and native build) in a subprocess of this virtualenv's interpreter; the JSON object it printed last.
    How the A/B scripts between two trees (bench.frame.ab_frame, bench.training.ab_train_step) measure each side."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    proc = subprocess.run([sys.executable, "-c", child, *args], cwd=tree, env=env, capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else 'failed'}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
