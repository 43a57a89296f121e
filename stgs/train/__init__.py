"""stgs.train: per-GOP StreamSTGS training from multi-view video (`stgs train`).

The budgets and TrainConfig are light; the trainer (torch) loads on first use (PEP 562), so that the command
line lists the budgets without it."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from stgs.train.config import BUDGETS, TrainConfig, budget

if TYPE_CHECKING:
    from stgs.train.run import train
    from stgs.train.trainer import DivergedError

__all__ = ["BUDGETS", "DivergedError", "TrainConfig", "budget", "train"]
_HOMES = {"train": "stgs.train.run", "DivergedError": "stgs.train.trainer"}


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
