"""What one GOP-stage iteration minimises (stgs.train.trainer's per-GOP loop), and the canonical regularisers
the coarse stage and stage A share with it.

One drawn (frame, camera) pair per iteration (stgs.train.images.view_draws): the temporal features of the frame's
window with feature noise λ·U(−0.5, 0.5) go through the deformation field; the deformed Gaussians are drawn (over
the frozen static layer's backdrop for that camera in a layered scene), through the camera's colour response
(stgs.train.camera_colour) and compared with the target (L1 + SSIM, again on the dynamic mask's pixels); the
auxiliary transformer's pass, the temporal Huber term over all features (its gradient and the window's written in
one pass), the canonical regularisers and the smoothness of the frame's feature grid are added (stgs.train.losses).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch

from stgs.metrics import ssim_map
from stgs.model.gop import Gaussians, GOPModel, flat_window, frame_time
from stgs.model.renderer import Backdrop, splat_over
from stgs.train import losses
from stgs.train.aux import AuxTransformer
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.config import TrainConfig
from stgs.train.images import Sample


class GOPLoss(NamedTuple):
    loss: torch.Tensor
    image: torch.Tensor
    """The drawn image (with gradients)."""
    target: torch.Tensor
    opacities: torch.Tensor
    """The drawn Gaussians' opacities, detached (for relocation's running average)."""


def canonical_regularisers(cfg: TrainConfig, model: GOPModel, opacities: torch.Tensor) -> torch.Tensor:
    """Opacity L1 and the smoothness of the (PLAS-sorted) colour and scale grids."""
    loss = cfg.opacity_weight * losses.opacity_l1(opacities)
    if cfg.smooth_weight:
        side = model.shape.grid_side
        loss = loss + cfg.smooth_weight * (losses.grid_smoothness(model.color, side)
                                           + losses.grid_smoothness(model.log_scale, side))
    return loss


def drop_gaussians(g: Gaussians, rate: float, gen: torch.Generator) -> Gaussians:
    """`g` with a random `rate` share of its Gaussians left out of the draw (opacity 0) and the others' opacity
    divided by 1 − rate (at most 1), so that a Gaussian's expected opacity stays what it was below that cap
    (DropGaussian, CVPR 2025). Each Gaussian then has to draw the views without its neighbours' help: stage A's
    guard against fitting the training cameras only. Rate 0: `g` itself, no draw from `gen`."""
    if rate <= 0:
        return g
    keep = torch.rand(g.opacities.shape[0], generator=gen) >= rate
    return dataclasses.replace(g, opacities=torch.where(keep, g.opacities / (1 - rate), 0).clamp(max=1.0))


def gop_loss(cfg: TrainConfig, gen: torch.Generator, model: GOPModel, aux: AuxTransformer | None, view: Sample,
             static: list[Backdrop] | None = None, deform: bool = True, colour: CameraColour | None = None
             ) -> GOPLoss:
    """One iteration's loss on the drawn `view` (its frame's position in the GOP and its camera's among the
    training cameras), drawing its noise from `gen`; `static`: the frozen static layer's backdrop for each
    training camera; `deform` False: the canonical Gaussians alone (the dynamic layer's warm-up,
    TrainConfig.dynamic_warmup); `colour`: the training cameras' colour responses the drawn images go through
    (fitted in the base stage, frozen here)."""
    shape = model.shape
    i, c, cam, target = view.frame, view.camera, view.cam, view.target
    noise = (torch.rand(model.features.shape[1], cfg.window * 16, generator=gen) - 0.5) * cfg.feature_noise
    if cfg.temporal_weight:  # one gradient buffer for the window, the smoothness term and the temporal term
        block, temporal = losses.window_and_temporal_huber(model.features, i, shape.window, cfg.huber_delta)
    else:
        block, temporal = model.feature_block(i), None
    window = flat_window(block) + noise
    center = cam.center.float()
    if deform:
        h = model.field.hidden(window, frame_time(i, shape.gop_size))
        g = model.apply_offsets(model.field.decode(h, model.xyz, center))
    else:
        h, g = None, model.canonical()
    backdrop = static[c] if static is not None else None
    img = as_recorded(colour, splat_over(backdrop, g, cam), c)
    ssim_values = ssim_map(img, target)
    loss = losses.photometric(img, target, cfg.lambda_ssim, ssim_values=ssim_values)
    dynamic = view.dynamic if cfg.dynamic else None
    if dynamic is not None:
        loss = loss + cfg.dynamic_weight * losses.photometric(img, target, cfg.lambda_ssim, dynamic, ssim_values)
    if aux is not None and deform:
        h_aux = aux(aux.tokens(model, i, window))  # the same noisy window the MLP sees
        g_aux = model.apply_offsets(model.field.decode(h_aux, model.xyz, center))
        img_aux = as_recorded(colour, splat_over(backdrop, g_aux, cam), c)
        loss = loss + cfg.aux_ssim_weight * (1 - losses.ssim(img_aux, target))
        assert h is not None  # deformed, so the MLP's hidden state is there
        loss = loss + cfg.distill_weight * losses.self_distillation(h, h_aux)
    if temporal is not None:
        loss = loss + cfg.temporal_weight * temporal
    loss = loss + canonical_regularisers(cfg, model, g.opacities)
    if cfg.smooth_weight:
        loss = loss + cfg.smooth_weight * losses.grid_smoothness(block[0], shape.grid_side)
    return GOPLoss(loss, img, target, g.opacities.detach())
