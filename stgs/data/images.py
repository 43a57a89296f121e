"""Image reading for datasets: size-checked, RGB float32 in [0, 1]."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import torch

from stgs.errors import StgsError


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from an image file's header (nothing decoded), or None when it is missing or unreadable."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()  # clear OpenImageIO's pending error message
        return None
    try:
        spec = inp.spec()
        return spec.width, spec.height
    finally:
        inp.close()


def check_image_sizes(root: Path, expected: Iterable[tuple[Path, tuple[int, int]]]) -> None:
    """Raise one StgsError unless every (file, (width, height)) has that size, reading only the headers."""
    bad, checked = [], 0
    for path, size in expected:
        checked += 1
        found = image_size(path)
        if found != size:
            what = "missing or not a readable image" if found is None else f"{found[0]}x{found[1]}"
            bad.append(f"{path.relative_to(root)} is {what}, expected {size[0]}x{size[1]}")
    if bad:
        raise StgsError(f"{root}: {len(bad)} of {checked} image(s) are missing or of another size, e.g. {bad[0]}")


def read_rgb8(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file; `size` = (H, W) it must have."""
    data = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if data is None:
        raise StgsError(f"{path}: missing or not a readable image")
    if size is not None and data.shape[:2] != tuple(size):
        raise StgsError(f"{path}: image is {data.shape[1]}x{data.shape[0]}, expected {size[1]}x{size[0]}")
    return cv2.cvtColor(data, cv2.COLOR_BGR2RGB)


def read_mask(path: Path, size: tuple[int, int]) -> torch.Tensor:
    """(H, W) bool foreground mask (any non-zero pixel is foreground)."""
    data = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if data is None:
        raise StgsError(f"{path}: missing or not a readable mask")
    if data.shape != tuple(size):
        raise StgsError(f"{path}: mask is {data.shape[1]}x{data.shape[0]}, expected {size[1]}x{size[0]}")
    return torch.from_numpy(data > 0)
