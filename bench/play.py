#!/usr/bin/env python3
"""Player per-GOP download/pre-decode and per-frame deform/splat at 65,536 Gaussians (same as `stgs bench play`)."""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "play", *sys.argv[1:]]))
