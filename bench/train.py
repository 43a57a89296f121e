#!/usr/bin/env python3
"""Held-out quality vs training time of finished `stgs train` runs (same as `stgs bench train`).

Usage: .venv/bin/python bench/train.py --runs MODEL_DIR[,MODEL_DIR...] [--plot docs/train_curves.png]
"""

import sys

from stgs.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "train", *sys.argv[1:]]))
