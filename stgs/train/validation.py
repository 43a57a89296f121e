"""What the training report scores as it goes: a model's mean PSNR and SSIM over a spread of views."""

from __future__ import annotations

from collections.abc import Callable

import torch

from stgs.camera import Camera
from stgs.metrics import psnr, ssim
from stgs.model.gop import GOPModel
from stgs.model.renderer import FrameRenderer, render_still
from stgs.model.static import StaticLayer
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.images import Views


@torch.no_grad()
def mean_scores(model: GOPModel, static: StaticLayer | None, views: Views, limit: int = 6,
                colour: CameraColour | None = None) -> tuple[float, float]:
    """Mean PSNR and SSIM of `model` (over `static` in a layered scene) at `limit` (frame, camera) pairs spread
    over the views; `colour`: the training cameras' colour responses (when `views` are the training views)."""
    renderer = FrameRenderer(model, static=static)
    return _scores(lambda f, cam: renderer.render(f, cam), views, limit, colour)


@torch.no_grad()
def still_scores(static: StaticLayer, views: Views, limit: int = 6,
                 colour: CameraColour | None = None) -> tuple[float, float]:
    """Mean PSNR and SSIM of a still scene (the static layer alone), as mean_scores."""
    return _scores(lambda f, cam: render_still(static, cam), views, limit, colour)


def _scores(render: Callable[[int, Camera], torch.Tensor], views: Views, limit: int,
            colour: CameraColour | None) -> tuple[float, float]:
    psnrs, ssims = [], []
    pairs = [(f, c) for f in range(len(views.frames)) for c in range(len(views.cameras))]
    step = max(1, len(pairs) // limit)
    for f, c in pairs[::step][:limit]:
        image = as_recorded(colour, render(f, views.cameras[c]), c).clamp(0, 1)
        target = views.target(f, c)
        psnrs.append(psnr(image, target))
        ssims.append(float(ssim(image, target)))
    return float(sum(psnrs) / len(psnrs)), float(sum(ssims) / len(ssims))
