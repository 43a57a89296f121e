"""stgs.train: per-GOP StreamSTGS training from multi-view video (`stgs train`).

The budgets and TrainConfig are light; the trainer (torch) loads on first use (PEP 562), so that the command
line lists the budgets without it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from stgs.lazy import lazy_attributes
from stgs.train.config import BUDGETS, TrainConfig, budget

if TYPE_CHECKING:
    from stgs.train.gop_report import DivergedError
    from stgs.train.run import train

__all__ = ["BUDGETS", "DivergedError", "TrainConfig", "budget", "train"]
__getattr__ = lazy_attributes(__name__, {"train": "stgs.train.run", "DivergedError": "stgs.train.gop_report"})
