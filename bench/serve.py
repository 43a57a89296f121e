#!/usr/bin/env python3
"""stgs serve vs nginx throughput and latency with wrk (same as `stgs bench serve`); see docs/BENCHMARKS.md."""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "serve", *sys.argv[1:]]))
