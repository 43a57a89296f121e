"""The splatter: `rasterize` and its two implementations.

`backend="auto"` picks the native C++ kernel for float32 CPU inputs when it is
built, and the pure-torch reference otherwise (float64, other devices, no
compiler). Both follow the numerics of docs/ARCHITECTURE.md; tests hold them to each other.
"""

from __future__ import annotations

import math
from typing import Literal

import torch

from stgs.limits import MAX_IMAGE_SIDE
from stgs.native.library import NativeUnavailableError, available, load
from stgs.render.project import Projected, project
from stgs.render.reference import composite_reference

Backend = Literal["auto", "native", "reference"]


def _value_range(t: torch.Tensor) -> tuple[float, float]:
    """(min, max) of a tensor; NaN propagates into both, so a non-finite input shows here."""
    if t.numel() == 0:
        return 0.0, 0.0
    lo, hi = torch.aminmax(t.detach())
    return lo.item(), hi.item()


def _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height,
                  background) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    shapes = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
              "opacities": (opacities, (n,)), "colors": (colors, (n, 3)),
              "viewmat": (viewmat, (4, 4)), "K": (K, (3, 3)), "background": (background, (3,))}
    ranges = {}
    for name, (t, shape) in shapes.items():
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"rasterize: {name} must be a torch.Tensor")
        if tuple(t.shape) != shape or n < 0:
            raise ValueError(f"rasterize: {name} has shape {tuple(t.shape)}, expected {shape} "
                             "(N Gaussians taken from means)")
        if t.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"rasterize: {name} has dtype {t.dtype}; use float32 or float64")
        ranges[name] = lo, hi = _value_range(t)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"rasterize: {name} contains NaN or Inf")
    dtypes = {t.dtype for t in (means, quats, scales, opacities, colors)}
    if len(dtypes) != 1:
        raise ValueError(f"rasterize: Gaussian inputs mix dtypes {sorted(map(str, dtypes))}")
    if ranges["opacities"][0] < 0 or ranges["opacities"][1] > 1:
        raise ValueError("rasterize: opacities must lie in [0, 1]")
    if ranges["scales"][0] < 0:
        raise ValueError("rasterize: scales must be non-negative (linear, not log)")
    for name, side in (("width", width), ("height", height)):
        if not isinstance(side, int) or not 0 < side <= MAX_IMAGE_SIDE:
            raise ValueError(f"rasterize: {name} must be an int in 1..{MAX_IMAGE_SIDE}, got {side!r}")


def choose_backend(dtype: torch.dtype, device: torch.device, backend: Backend = "auto") -> str:
    """The implementation `rasterize` will run for inputs of this dtype and device."""
    if backend == "reference":
        return "reference"
    native_ok = dtype == torch.float32 and device.type == "cpu"
    if backend == "native":
        if not native_ok:
            raise ValueError("rasterize: the native backend takes float32 CPU tensors")
        load()  # raises NativeUnavailableError with the build error
        return "native"
    if backend != "auto":
        raise ValueError(f"rasterize: unknown backend {backend!r}")
    return "native" if native_ok and available() else "reference"


def needs_grad(*tensors: torch.Tensor) -> bool:
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
              opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
              K: torch.Tensor, width: int, height: int, background: torch.Tensor | None = None,
              backend: Backend = "auto") -> torch.Tensor:
    """Splat N Gaussians into an (height, width, 3) image (docs/ARCHITECTURE.md, "The splatter").

    means (N,3), quats (N,4) wxyz (normalised inside), scales (N,3) linear,
    opacities (N,) in [0,1], colors (N,3), viewmat 4x4 world-to-camera (OpenCV
    axes), K 3x3, background (3,) default black. The output dtype follows the
    inputs; the result is differentiable in every Gaussian input and the
    background. NaN/Inf inputs raise ValueError.
    """
    dtype = means.dtype
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=means.device)
    _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background)
    which = choose_backend(dtype, means.device, backend)
    if which == "reference":
        proj = project(means.to(torch.float64), quats.to(torch.float64),
                       scales.to(torch.float64), opacities, viewmat, K)
        return composite_reference(proj, opacities, colors, width, height, background.to(dtype))
    from stgs.render import native

    if not needs_grad(means, quats, scales, opacities, colors, background):
        proj = native.project_native(means, quats, scales, opacities, viewmat, K)
        image, _ = native.raster_forward(proj.means2d, proj.conics, native.f32(opacities),
                                         native.f32(colors), native.f32(background),
                                         proj.depths, proj.extents, width, height)
        return image
    proj = native.project_trainable(means, quats, scales, opacities, viewmat, K)
    return native.NativeComposite.apply(proj.means2d, proj.conics, opacities, colors, background, proj.depths,
                                        proj.extents, width, height)


__all__ = ["MAX_IMAGE_SIDE", "NativeUnavailableError", "Projected", "choose_backend", "rasterize"]
