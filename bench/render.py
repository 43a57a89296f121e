#!/usr/bin/env python3
"""Splatter + deform accuracy vs time (same as `stgs bench render`); see docs/BENCHMARKS.md.

Usage: .venv/bin/python bench/render.py [--sizes 16384,65536,147456] [--repeats 5]
"""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "render", *sys.argv[1:]]))
