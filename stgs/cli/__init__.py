"""stgs.cli: the `stgs` command and `stgs demo`, the top layer that drives the stages (nothing imports it)."""

from stgs.cli.commands import build_parser, main
from stgs.cli.model import train_overrides

__all__ = ["build_parser", "main", "train_overrides"]
