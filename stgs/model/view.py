"""Render one frame of a GOP model from a camera: deform, then splat."""

from __future__ import annotations

import torch

from stgs.camera import Camera, orbit
from stgs.model.gop import Gaussians, GOPModel
from stgs.native.build import available
from stgs.render import rasterize


class FrameRenderer:
    """Renders frames of one GOP, using the native deform and splat when they are built."""

    def __init__(self, model: GOPModel, native: bool | None = None, precision: str = "fp32"):
        """precision: arithmetic of the native deformation ("fp32" or "bf16", an accuracy knob)."""
        self.model = model
        self.native = available() if native is None else native
        self.precision = precision
        self._weights = None
        if self.native:
            from stgs.model.native_deform import PackedWeights, check_precision

            check_precision(precision)
            self._weights = PackedWeights(model)
        elif precision != "fp32":
            raise ValueError(f"deform precision {precision!r} needs the native build")

    @torch.no_grad()
    def gaussians(self, frame: int, camera: Camera) -> Gaussians:
        """The deformed Gaussians of `frame` seen from `camera` (culled to its view when native)."""
        if not self.native:
            return self.model.deform(frame, camera.center.float())
        from stgs.model.native_deform import deform_native

        return deform_native(self.model, frame, camera.center.float(), self._weights,
                             camera.viewmat, camera.K, camera.width, camera.height, self.precision)

    @torch.no_grad()
    def render(self, frame: int, camera: Camera, background: torch.Tensor | None = None) -> torch.Tensor:
        """(H, W, 3) float32 image of `frame` from `camera`."""
        return self.splat(self.gaussians(frame, camera), camera, background)

    @torch.no_grad()
    def splat(self, g: Gaussians, camera: Camera, background: torch.Tensor | None = None) -> torch.Tensor:
        """(H, W, 3) float32 image of deformed Gaussians from `camera`."""
        bg = background.float() if background is not None else None
        return rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, camera.viewmat.float(),
                         camera.K.float(), camera.width, camera.height, bg,
                         backend="auto" if self.native else "reference")


def framing_orbit(model: GOPModel, count: int, width: int, height: int, fov_x_deg: float = 60.0) -> list[Camera]:
    """`count` cameras on a circle that frames the visible canonical Gaussians of a GOP."""
    visible = torch.sigmoid(model.opacity_logit.detach()) > 0.05
    pts = model.xyz.detach()[visible] if visible.any() else model.xyz.detach()
    center = pts.median(0).values
    radius = float((pts - center).norm(dim=1).quantile(0.9)) * 2.5 + 1e-3
    return orbit(count, radius, float(center[1]) + 0.3 * radius, tuple(center.tolist()), width, height, fov_x_deg)
