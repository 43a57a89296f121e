#!/usr/bin/env python3
"""Packager rate/distortion/time per QP and preset, PLAS vs no sort (same as `stgs bench pack`)."""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "pack", *sys.argv[1:]]))
