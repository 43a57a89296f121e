"""File output that never leaves a half-written file behind, and PNG I/O."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

FILE_MODE = 0o644
"""Mode of every file we write (what a static web server or CDN origin expects)."""
DIR_MODE = 0o755


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write data to path through a temp file in the same folder and rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, FILE_MODE)  # mkstemp makes 0600; published files must be readable by any server
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] -> uint8 RGB (clipped, rounded)."""
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def encode_png(image: torch.Tensor) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def save_figure(fig, path: Path) -> None:
    """A matplotlib figure as a PNG (110 dpi), written atomically; the figure is closed."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def save_png(path: Path, image: torch.Tensor) -> None:
    """Write an (H, W, 3) float RGB image in [0, 1] as an 8-bit PNG, atomically."""
    atomic_write_bytes(Path(path), encode_png(image))


def load_png(path: Path) -> torch.Tensor:
    """Read an RGB PNG as an (H, W, 3) float32 tensor in [0, 1]."""
    data = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if data is None:
        raise OSError(f"{path}: not a readable image")
    return torch.from_numpy(cv2.cvtColor(data, cv2.COLOR_BGR2RGB)).float() / 255.0


def image_grid(images: list[torch.Tensor], columns: int) -> torch.Tensor:
    """Tile equally sized (H, W, 3) images row-major, padding the last row with black."""
    h, w, _ = images[0].shape
    rows = -(-len(images) // columns)
    sheet = torch.zeros(rows * h, columns * w, 3)
    for i, img in enumerate(images):
        r, c = divmod(i, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = img
    return sheet
