"""Canonical Gaussian attributes <-> five quantised images (docs/ARCHITECTURE.md, "The model and its compression").

| image    | channels | stored            | clip     | levels |
|----------|----------|-------------------|----------|--------|
| position | 3        | xyz               | GOP min/max per channel | 2^16 |
| scale    | 3        | log scale         | GOP min/max per channel | 2^6  |
| rotation | 4        | quaternion wxyz   | [-1, 2]  | 2^7    |
| opacity  | 1        | logit             | [-4, 4]  | 2^6    |
| color    | 3        | colour before relu| [0, 4]   | 2^16   |

Values are clipped, normalised to [0, 1] with the range, and quantised to the
level count; the integer codes are the image pixels (uint8 for <= 2^8 levels,
else uint16). Gaussian i of the (PLAS-sorted) GOP is pixel (i // S, i % S).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stgs.model.gop import GOPModel
from stgs.model.static import StaticLayer


@dataclass(frozen=True)
class AttributeSpec:
    name: str
    """Image name in the keyframe container."""
    param: str
    """GOPModel parameter it stores."""
    channels: int
    levels: int
    clip: tuple[float, float] | None
    """Fixed range; None: the GOP's per-channel min/max."""

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.levels <= 256 else np.uint16)


OPACITY_LOGIT_RANGE = (-4.0, 4.0)
"""The stream's canonical opacity logit range: sigmoid(-4) ≈ 0.018 is the faintest a packaged Gaussian can be."""

SPECS = (
    AttributeSpec("position", "xyz", 3, 1 << 16, None),
    AttributeSpec("scale", "log_scale", 3, 1 << 6, None),
    AttributeSpec("rotation", "rotation", 4, 1 << 7, (-1.0, 2.0)),
    AttributeSpec("opacity", "opacity_logit", 1, 1 << 6, OPACITY_LOGIT_RANGE),
    AttributeSpec("color", "color", 3, 1 << 16, (0.0, 4.0)),
)
"""The five attribute images, in container order."""


def value_range(values: torch.Tensor) -> torch.Tensor:
    """(2, C) per-column [min, max] of `values` (N, C), a flat column widened so that it can be normalised."""
    lo, hi = values.amin(0), values.amax(0)
    hi = torch.where(hi - lo > 1e-12, hi, lo + 1e-6)
    return torch.stack([lo, hi]).float()


def attribute_range(spec: AttributeSpec, values: torch.Tensor) -> torch.Tensor:
    """(2, C) [lo, hi] used to normalise `values` (N, C)."""
    if spec.clip is None:
        return value_range(values)
    lo = torch.full((spec.channels,), spec.clip[0])
    hi = torch.full((spec.channels,), spec.clip[1])
    return torch.stack([lo, hi]).float()


def _values(model: GOPModel | StaticLayer, spec: AttributeSpec) -> torch.Tensor:
    return getattr(model, spec.param).detach().float().reshape(-1, spec.channels)


def quantize(spec: AttributeSpec, values: torch.Tensor, rng: torch.Tensor, side: int) -> np.ndarray:
    """(N, C) values -> (S, S, C) integer codes."""
    lo, hi = rng[0], rng[1]
    unit = ((values.clamp(lo, hi) - lo) / (hi - lo)).clamp(0, 1)
    codes = torch.round(unit * (spec.levels - 1)).to(torch.int64)
    return codes.reshape(side, side, spec.channels).numpy().astype(spec.dtype)


def dequantize(spec: AttributeSpec, codes: np.ndarray, rng: torch.Tensor) -> torch.Tensor:
    """(S, S, C) codes -> (N, C) float32 values."""
    if int(codes.max(initial=0)) >= spec.levels:
        raise ValueError(f"{spec.name}: code {int(codes.max())} exceeds {spec.levels - 1}")
    unit = torch.from_numpy(codes.astype(np.float32)).reshape(-1, spec.channels) / (spec.levels - 1)
    return unit * (rng[1] - rng[0]) + rng[0]


def encode_attributes(model: GOPModel | StaticLayer, side: int,
                      specs: tuple[AttributeSpec, ...] = SPECS) -> dict[str, tuple[np.ndarray, torch.Tensor]]:
    """name -> (codes (S, S, C), range (2, C)) for every attribute image, at the levels of `specs` (SPECS, or a
    lossy keyframe's: stgs.codec.quant.KeyframeQuant)."""
    out = {}
    for spec in specs:
        values = _values(model, spec)
        rng = attribute_range(spec, values)
        out[spec.name] = (quantize(spec, values, rng, side), rng)
    return out


def apply_attributes(model: GOPModel | StaticLayer, decoded: dict[str, torch.Tensor]) -> None:
    """Load dequantised (N, C) attributes into the model's canonical parameters."""
    with torch.no_grad():
        for spec in SPECS:
            param = getattr(model, spec.param)
            param.copy_(decoded[spec.name].reshape(param.shape))
