#!/usr/bin/env python3
"""Synthetic fit: fidelity vs fit iterations (same as `stgs bench synth`); see docs/BENCHMARKS.md."""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "synth", *sys.argv[1:]]))
