"""stgs.train: per-GOP StreamSTGS training from multi-view video (`stgs train`)."""

from stgs.train.config import BUDGETS, TrainConfig, budget
from stgs.train.run import train
from stgs.train.trainer import DivergedError

__all__ = ["BUDGETS", "DivergedError", "TrainConfig", "budget", "train"]
