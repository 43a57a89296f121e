"""Fuzzing cases per second of each parser, and any finding (`python -m bench.fuzzing.fuzz`): the targets of
`stgs.testing.fuzz`, run for as long as asked with fresh random cases (docs/SECURITY.md, "Fuzzing"; the test suite
runs a derandomised few hundred per target in tests/fuzz)."""

from __future__ import annotations

import argparse
import time

from stgs.testing.fuzz import MEMORY_BOUND_MB, TARGETS, fuzz, peak_rss_mb


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=20_000, help="cases per target (default: 20000)")
    parser.add_argument("--target", choices=sorted(TARGETS), action="append", help="only these (repeatable)")
    args = parser.parse_args(argv)
    print("| target | cases | seconds | cases/s | peak RSS growth |\n|---|---|---|---|---|")
    for name in args.target or TARGETS:
        TARGETS[name].inputs()  # builds the target's seeds (an encode, a model) outside the measured growth
        before = peak_rss_mb()
        start = time.perf_counter()
        count = fuzz(name, args.examples, derandomize=False)
        seconds = time.perf_counter() - start
        grown = peak_rss_mb() - before
        print(f"| {name} | {count} | {seconds:.0f} | {count / seconds:.0f} | {grown:.0f} MB |", flush=True)
        if grown > MEMORY_BOUND_MB:
            raise SystemExit(f"{name}: peak RSS grew by {grown:.0f} MB (bound {MEMORY_BOUND_MB} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
