"""What a GOP's training reports (train_report.json's `gops`, and its checkpoints), and how a run ends when the loss
diverges."""

from __future__ import annotations

from dataclasses import dataclass, field

from stgs.errors import StgsError


class DivergedError(StgsError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


@dataclass
class GOPReport:
    gop: int
    seconds: float = 0.0
    iterations: int = 0
    final_loss: float = 0.0
    train_psnr: float = 0.0
    val_psnr: float | None = None
    val_ssim: float | None = None
    relocated: int = 0
    pruned: int = 0
    curve: list[dict] = field(default_factory=list)
    """(iteration, seconds, loss, validation PSNR and SSIM) samples: accuracy vs time."""
    peak_rss_mb: float | None = None
    """The training process's peak memory when the GOP was saved (stgs.memory.process_peak_rss_mb)."""
