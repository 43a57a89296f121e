"""Render one frame of a GOP model from a camera: deform, then splat.

Every model render (training, evaluation, playback) goes through `splat`, which
leaves out Gaussians outside the camera's guard band before rasterising: the
view frustum widened sideways by GUARD_BAND and starting NEAR_CLIP in front of
the camera. A Gaussian whose mean projects far outside the image, seen at a
grazing angle, gets a screen footprint from the EWA linearisation that can
cover the whole image (a wall Gaussian beside a camera of a dome rig becomes a
flat veil); one just in front of the lens fills it (in a dome, the other
cameras' housings are part of the scene, and a held-out camera sits inside
its own). The splatter itself follows docs/ARCHITECTURE.md to the letter; the guard band
is the model's drawing rule, as frustum culling is in other 3DGS renderers
(the reference 3DGS rasteriser also drops means nearer than 0.2).
"""

from __future__ import annotations

import torch

from stgs.camera import Camera, orbit
from stgs.model.gop import Gaussians, GOPModel
from stgs.model.static import StaticLayer, merge
from stgs.native.library import available
from stgs.render import Backend, rasterize
from stgs.render.fixed import FixedLayerView

GUARD_BAND = 1.3
"""A Gaussian is drawn only when its mean projects within this many times the image's half-extent
(measured from the principal point, in each axis)..."""
NEAR_CLIP = 0.2
"""... and lies more than this far in front of the camera (scene units)."""


def guard_limits(camera: Camera, margin: float = GUARD_BAND, near: float = NEAR_CLIP) -> tuple[float, float, float]:
    """(near, x limit, y limit): a camera-space point is in the guard band when z > near,
    |x| <= x limit * z and |y| <= y limit * z."""
    K = camera.K.double()
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    return near, margin * max(cx, camera.width - cx) / fx, margin * max(cy, camera.height - cy) / fy


def in_guard_band(means: torch.Tensor, camera: Camera, margin: float = GUARD_BAND,
                  near: float = NEAR_CLIP) -> torch.Tensor:
    """(N,) bool: whether each mean lies deeper than `near` and projects inside `margin` x the image's
    half-extent."""
    view = camera.viewmat.to(means.dtype)
    cam = means.detach() @ view[:3, :3].T + view[:3, 3]
    z = cam[:, 2]
    near, limit_x, limit_y = guard_limits(camera, margin, near)
    return (z > near) & (cam[:, 0].abs() <= limit_x * z) & (cam[:, 1].abs() <= limit_y * z)


def guarded_opacities(g: Gaussians, camera: Camera) -> torch.Tensor:
    """g's opacities with those outside the guard band (in_guard_band) set to 0, as the frame path draws them."""
    return g.opacities * in_guard_band(g.means, camera).to(g.opacities.dtype)


def splat(g: Gaussians, camera: Camera, background: torch.Tensor | None = None,
          backend: Backend = "auto", guarded: bool = False) -> torch.Tensor:
    """(H, W, 3) image of deformed Gaussians from `camera` (differentiable); the guard band is applied unless
    `guarded` says g already had it (FrameRenderer.gaussians of a native renderer)."""
    opacities = g.opacities if guarded else guarded_opacities(g, camera)
    dtype = g.means.dtype
    return rasterize(g.means, g.quats, g.scales, opacities, g.colors, camera.viewmat.to(dtype),
                     camera.K.to(dtype), camera.width, camera.height, background, backend=backend)


def static_view(static: StaticLayer, camera: Camera) -> Gaussians:
    """The static layer as `camera` draws it: activated, view-dependent colour evaluated, guard band applied."""
    g = static.gaussians(camera.center.float())
    return Gaussians(g.means.detach(), g.quats.detach(), g.scales.detach(),
                     guarded_opacities(g, camera).detach(), g.colors.detach())


Backdrop = Gaussians | FixedLayerView
"""A frozen static layer as one camera draws it (static_backdrops)."""


def static_backdrops(static: StaticLayer, cameras: list[Camera]) -> list[Backdrop]:
    """The frozen static layer as each camera draws it, for training a dynamic layer over it: natively kept
    (projected, binned and rendered once, stgs.render.fixed), so that each draw composites and differentiates
    only the tiles the dynamic layer reaches; otherwise its Gaussians, splatted with the dynamic ones."""
    views = [static_view(static, cam) for cam in cameras]
    if not available():
        return list[Backdrop](views)
    return [FixedLayerView(g.means, g.quats, g.scales, g.opacities, g.colors, cam.viewmat.float(), cam.K.float(),
                           cam.width, cam.height) for g, cam in zip(views, cameras, strict=True)]


def splat_over(backdrop: Backdrop | None, g: Gaussians, camera: Camera) -> torch.Tensor:
    """(H, W, 3) image of `g` (deformed, differentiable) drawn with a backdrop of `static_backdrops` for
    `camera` in one splat (g alone for None): the image of `splat` of both layers."""
    if backdrop is None:
        return splat(g, camera)
    if isinstance(backdrop, Gaussians):
        return splat(merge(backdrop, g), camera)
    return backdrop.draw(g.means, g.quats, g.scales, guarded_opacities(g, camera), g.colors)


def camera_key(camera: Camera) -> tuple:
    """Everything about a camera that changes how a static Gaussian is drawn (pose, intrinsics, size)."""
    return (camera.viewmat.numpy().tobytes(), camera.K.numpy().tobytes(), camera.width, camera.height)


class StaticDrawer:
    """A scene's static layer as its GOPs' renderers draw it. Kept for the last camera: its per-view work
    (activation, view-dependent colour, guard band); natively, once a camera and background have been drawn
    twice in a row, its projection, tile lists and image alone (stgs.render.fixed), so that a frame composites
    only the tiles the dynamic layer reaches. A player gives one drawer to every GOP's renderer, so a still
    camera keeps the layer across GOP boundaries."""

    def __init__(self, layer: StaticLayer):
        self.layer = layer
        self._view: tuple[tuple, Gaussians] | None = None
        self._kept: tuple[tuple, FixedLayerView | None] | None = None
        """(camera and background, the layer kept for them from their second frame in a row on)."""

    def gaussians(self, camera: Camera) -> Gaussians:
        """The static layer as `camera` draws it (always guarded), reused while the camera does not move."""
        key = camera_key(camera)
        if self._view is None or self._view[0] != key:
            self._view = (key, static_view(self.layer, camera))
        return self._view[1]

    def kept_view(self, camera: Camera, background: torch.Tensor) -> FixedLayerView | None:
        """The layer kept for this camera and (float32) background, or None on the first frame of a pair (the
        caller splats both layers as usual: a camera that moves every frame never pays for a kept layer)."""
        key = (camera_key(camera), background.numpy().tobytes())
        if self._kept is None or self._kept[0] != key:
            self._kept = (key, None)
            return None
        if self._kept[1] is None:
            s = self.gaussians(camera)
            self._kept = (key, FixedLayerView(s.means, s.quats, s.scales, s.opacities, s.colors,
                                              camera.viewmat.float(), camera.K.float(), camera.width,
                                              camera.height, background))
        return self._kept[1]


class FrameRenderer:
    """Renders frames of one GOP (and the scene's static layer, if any), using the native deform and splat
    when they are built. Only the dynamic layer is deformed; the static layer is drawn through a
    StaticDrawer, which keeps its per-view work while the camera stays put."""

    def __init__(self, model: GOPModel, native: bool | None = None, precision: str = "fp32",
                 static: StaticLayer | StaticDrawer | None = None):
        """precision: arithmetic of the native deformation (stgs.model.precision.PRECISIONS: "fp32", "bf16"
        or "int16", the last two accuracy knobs); static: the scene's static layer, or a drawer of it shared
        with the other GOPs' renderers."""
        self.model = model
        self.static_drawer = StaticDrawer(static) if isinstance(static, StaticLayer) else static
        self.static = self.static_drawer.layer if self.static_drawer is not None else None
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
    def gaussians(self, frame: int, camera: Camera, window: list[torch.Tensor] | None = None) -> Gaussians:
        """The static layer's Gaussians (if any) followed by the deformed dynamic ones of `frame`, seen from
        `camera`; when native, those off its view or outside its guard band have opacity 0 (`guarded`).
        `window`: the frame's feature frames where the model does not hold them (GOPModel.feature_window)."""
        dynamic = self.dynamic_gaussians(frame, camera, window)
        static = self.static_gaussians(camera)
        return dynamic if static is None else merge(static, dynamic)

    @torch.no_grad()
    def dynamic_gaussians(self, frame: int, camera: Camera, window: list[torch.Tensor] | None = None) -> Gaussians:
        """The GOP's deformed Gaussians of `frame` (guarded when native)."""
        if not self.native:
            return self.model.deform(frame, camera.center.float(), window)
        from stgs.model.native_deform import deform_native

        return deform_native(self.model, frame, camera.center.float(), self._weights,
                             camera.viewmat, camera.K, camera.width, camera.height, self.precision,
                             guard=guard_limits(camera), window=window)

    def static_gaussians(self, camera: Camera) -> Gaussians | None:
        """The static layer as `camera` draws it (always guarded), reused while the camera does not move."""
        return None if self.static_drawer is None else self.static_drawer.gaussians(camera)

    @property
    def guarded(self) -> bool:
        """Whether `gaussians` already applies the guard band (so `splat` need not)."""
        return self.native

    @torch.no_grad()
    def render(self, frame: int, camera: Camera, background: torch.Tensor | None = None,
               window: list[torch.Tensor] | None = None) -> torch.Tensor:
        """(H, W, 3) float32 image of `frame` from `camera`."""
        return self.draw(self.dynamic_gaussians(frame, camera, window), camera, background)

    @torch.no_grad()
    def draw(self, dynamic: Gaussians, camera: Camera, background: torch.Tensor | None = None) -> torch.Tensor:
        """(H, W, 3) float32 image of the static layer (if any) and `dynamic` (from `dynamic_gaussians` of this
        camera) in one splat; natively, from the second frame of a still camera on, with the static layer kept
        (StaticDrawer.kept_view: the same pixels)."""
        drawer = self.static_drawer
        if drawer is not None and self.native:
            bg = torch.zeros(3) if background is None else background.detach().float()
            if (kept := drawer.kept_view(camera, bg)) is not None:
                return kept.draw(dynamic.means, dynamic.quats, dynamic.scales, dynamic.opacities, dynamic.colors)
        g = dynamic if drawer is None else merge(drawer.gaussians(camera), dynamic)
        return self.splat(g, camera, background, guarded=self.guarded)

    @torch.no_grad()
    def splat(self, g: Gaussians, camera: Camera, background: torch.Tensor | None = None,
              guarded: bool = False) -> torch.Tensor:
        """(H, W, 3) float32 image of deformed Gaussians from `camera`; `guarded`: g came from
        `gaussians(frame, camera)` of a guarded renderer, so the guard band is not applied again."""
        bg = background.float() if background is not None else None
        return splat(g, camera, bg, "auto" if self.native else "reference", guarded)


@torch.no_grad()
def render_still(static: StaticLayer | StaticDrawer, camera: Camera, background: torch.Tensor | None = None,
                 native: bool | None = None) -> torch.Tensor:
    """(H, W, 3) float32 image of a still scene (its static layer alone, no GOP) from `camera`."""
    drawer = static if isinstance(static, StaticDrawer) else StaticDrawer(static)
    native = available() if native is None else native
    bg = background.float() if background is not None else None
    return splat(drawer.gaussians(camera), camera, bg, "auto" if native else "reference", guarded=True)


def framing_orbit(model: GOPModel | StaticLayer, count: int, width: int, height: int,
                  fov_x_deg: float = 60.0) -> list[Camera]:
    """`count` cameras on a circle that frames the visible canonical Gaussians of a GOP (or a still's static
    layer)."""
    visible = torch.sigmoid(model.opacity_logit.detach()) > 0.05
    pts = model.xyz.detach()[visible] if visible.any() else model.xyz.detach()
    center = pts.median(0).values
    radius = float((pts - center).norm(dim=1).quantile(0.9)) * 2.5 + 1e-3
    return orbit(count, radius, float(center[1]) + 0.3 * radius, tuple(center.tolist()), width, height, fov_x_deg)
