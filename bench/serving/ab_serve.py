#!/usr/bin/env python3
"""A/B of `stgs serve`'s cost per request between two source trees (server CPU per request under wrk).

Each round starts one tree's server (2 workers, --quiet) on a free loopback port, runs wrk (one thread,
keep-alive, round-robin over every segment of a packaged scene) and reads the workers' CPU time (utime +
stime of /proc/PID/stat) before and after; then the other tree, the order alternating by round. Like
bench/frame/ab_frame.py, it compares builds within one run because this machine's speed drifts.

The editable install maps `stgs` to this checkout, so each tree runs from a folder of symlinks to its own stgs/
(a tree from before server, client, packager, harness and cli moved under stgs/ gets those linked in).

Usage: .venv/bin/python -m bench.serving.ab_serve OLD_TREE NEW_TREE DASH_DIR [--rounds 4] [--clients 64] [--seconds 6]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.serving.serve import WRK_SCRIPT, check_serves, cpu_per_request, free_port, wait_for
from stgs.server.workers import worker_pids
from stgs.tree import SEGMENT_SUFFIXES

TOP_LEVEL = ("server", "client", "packager", "harness", "cli")
"""Packages that older trees kept at the top level and mapped into stgs."""


def import_root(tree: Path, tmp: Path) -> Path:
    """A folder whose stgs/ is tree's stgs/, plus an older tree's top-level packages (for PYTHONPATH)."""
    root = tmp / tree.name
    (root / "stgs").mkdir(parents=True)
    for entry in (tree / "stgs").iterdir():
        (root / "stgs" / entry.name).symlink_to(entry)
    for name in TOP_LEVEL:
        if (tree / name).is_dir() and not (tree / "stgs" / name).exists():
            (root / "stgs" / name).symlink_to(tree / name)
    return root


def measure(root: Path, dash: Path, script: Path, first: str, clients: int, seconds: int) -> tuple[float, float]:
    """(server CPU µs per request, requests per second) of one run."""
    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(root))
    # cwd=root: `python -m` puts the working directory first on sys.path, ahead of PYTHONPATH
    server = subprocess.Popen([sys.executable, "-m", "stgs.cli", "serve", str(dash), "--port", str(port),
                               "--workers", "2", "--quiet"], cwd=root, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        wait_for(port)
        check_serves(port, first)
        us, rps, _ = cpu_per_request(worker_pids(server.pid), port, script, clients, seconds)
    finally:
        server.terminate()
        server.wait(timeout=30)
    return us, rps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("dash", type=Path, help="a packaged scene (stgs pack output)")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--clients", type=int, default=64)
    parser.add_argument("--seconds", type=int, default=6)
    args = parser.parse_args()
    dash = args.dash.resolve()
    paths = sorted(str(p.relative_to(dash)) for p in dash.rglob("*") if p.suffix in SEGMENT_SUFFIXES)
    if not paths:
        raise SystemExit(f"{dash}: no segments (expected a folder written by stgs pack)")
    results: dict[str, list[tuple[float, float]]] = {"old": [], "new": []}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        script = tmp / "paths.lua"
        script.write_text(WRK_SCRIPT.format(paths=", ".join(f'"/{p}"' for p in paths)))
        roots = {}
        for name, tree in (("old", args.old.resolve()), ("new", args.new.resolve())):
            if not all((tree / d).is_dir() for d in ("stgs", "server", "client")):
                raise SystemExit(f"{tree} is not a streamstgs source tree")
            roots[name] = import_root(tree, tmp / name)
        for r in range(args.rounds):
            for name in ("old", "new") if r % 2 == 0 else ("new", "old"):
                results[name].append(measure(roots[name], dash, script, paths[0], args.clients, args.seconds))
                us, rps = results[name][-1]
                print(f"round {r + 1} {name}: {us:.0f} us CPU per request, {rps:.0f} requests/s", flush=True)
    print("\n| tree | server CPU µs per request (median) | requests/s (median) |")
    print("|---|---|---|")
    for name, runs in results.items():
        print(f"| {name} | {statistics.median(u for u, _ in runs):.0f} | {statistics.median(r for _, r in runs):.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
