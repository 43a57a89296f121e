#!/usr/bin/env python3
"""Simulated vs emulated QoE and playbacks per second of each engine (same as `stgs bench sim`)."""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "sim", *sys.argv[1:]]))
