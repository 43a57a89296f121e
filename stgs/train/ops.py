"""What changes the set or order of the Gaussians during training, and the optimizer-state surgery it needs
(as gsplat's strategy/ops): relocation of dead Gaussians (3DGS-MCMC), PLAS sorting, pruning at the end.

A Gaussian's parameters are rows of several tensors (GAUSSIAN_AXIS); whatever moves, copies or resets rows
does the same to those rows of Adam's moments, so the optimizer never carries a row's momentum to another."""

from __future__ import annotations

import math

import torch

from stgs.codec.attributes import OPACITY_LOGIT_RANGE
from stgs.codec.plas import plas_order, sort_key
from stgs.codec.plas_config import PLASConfig
from stgs.model.gop import GOPModel
from stgs.train.aux import AuxTransformer
from stgs.train.camera_colour import CameraColour
from stgs.train.config import TrainConfig

GAUSSIAN_AXIS = {"xyz": 0, "log_scale": 0, "rotation": 0, "opacity_logit": 0, "color": 0, "features": 1}
"""Which axis of each per-Gaussian parameter indexes the Gaussians."""


class Optimizer:
    """Adam over named parameter groups, with per-Gaussian row surgery (permute, reset) for sorting and relocation."""

    def __init__(self, model: GOPModel, cfg: TrainConfig, extent: float, aux: AuxTransformer | None,
                 canonical_only: bool = False, fused: bool = True, colour: CameraColour | None = None):
        """`colour`: the training cameras' colour responses, fitted beside the model (the base stage)."""
        lr = cfg.lr
        groups = [("xyz", [model.xyz], lr.position * extent), ("log_scale", [model.log_scale], lr.scale),
                  ("rotation", [model.rotation], lr.rotation), ("opacity_logit", [model.opacity_logit], lr.opacity),
                  ("color", [model.color], lr.color)]
        if not canonical_only:
            groups += [("features", [model.features], lr.features), ("field", list(model.field.parameters()), lr.field)]
            if aux is not None:
                groups.append(("aux", list(aux.parameters()), lr.aux))
        if colour is not None:
            groups.append(("camera_colour", list(colour.parameters()), lr.camera_colour))
        # The fused CPU kernel: one pass over each parameter (every step updates all the temporal features).
        self.opt = torch.optim.Adam([{"params": p, "lr": r, "name": n} for n, p, r in groups], eps=1e-15,
                                    fused=fused)
        self.model, self.cfg, self.extent = model, cfg, extent

    def set_progress(self, fraction: float) -> None:
        lr = self.cfg.lr
        for g in self.opt.param_groups:
            if g["name"] == "xyz":
                g["lr"] = log_lerp(lr.position, lr.position_final, fraction) * self.extent
            elif g["name"] == "field":
                g["lr"] = log_lerp(lr.field, lr.field_final, fraction)

    def rows(self, name: str, index: torch.Tensor, source: torch.Tensor | None = None) -> None:
        """Reset (source None) or copy (from rows `source`) the Adam state of Gaussian rows `index`."""
        param = getattr(self.model, name)
        state = self.opt.state.get(param)
        if not state:
            return
        axis = GAUSSIAN_AXIS[name]
        for key in ("exp_avg", "exp_avg_sq"):
            t = state[key]
            if source is None:
                t.index_fill_(axis, index, 0.0)
            else:
                t.index_copy_(axis, index, t.index_select(axis, source))

    def permute(self, order: torch.Tensor) -> None:
        with torch.no_grad():
            for name, axis in GAUSSIAN_AXIS.items():
                param = getattr(self.model, name)
                param.copy_(param.index_select(axis, order))
                state = self.opt.state.get(param)
                for key in ("exp_avg", "exp_avg_sq"):
                    if state:
                        state[key].copy_(state[key].index_select(axis, order))


def log_lerp(a: float, b: float, t: float) -> float:
    return math.exp(math.log(a) * (1 - t) + math.log(b) * t)


@torch.no_grad()
def relocate(model: GOPModel, opt: Optimizer, level: torch.Tensor, dead_opacity: float, gen: torch.Generator) -> int:
    """Move dead Gaussians (drawn opacity `level`, opacity_level's mean or peak, below `dead_opacity`) onto live
    ones sampled by it, splitting the opacity (3DGS-MCMC); the Adam state of both rows restarts. Returns how many
    moved.

    A live Gaussian gives at most as many copies as keep every share at twice `dead_opacity` or more
    (`copies_allowed`); the dead slots beyond that wait for the next relocation. Without the cap a faint live
    set (a small dynamic layer early on) is split into copies born dead, which the next relocation splits
    again, until every Gaussian is dead."""
    dead = torch.nonzero(level < dead_opacity).squeeze(1)
    alive = level >= dead_opacity
    if len(dead) == 0 or not alive.any():
        return 0
    probs = torch.where(alive, level, torch.zeros_like(level))
    src = torch.multinomial(probs, len(dead), replacement=True, generator=gen)
    base = torch.sigmoid(model.opacity_logit)
    keep = _copy_rank(src) < copies_allowed(base, dead_opacity)[src]
    dead, src = dead[keep], src[keep]
    if len(dead) == 0:
        return 0
    counts = torch.bincount(src, minlength=len(level)).float()
    split = 1 - (1 - base[src]).clamp_min(1e-6) ** (1 / (counts[src] + 1))
    for name, axis in GAUSSIAN_AXIS.items():
        param = getattr(model, name)
        param.index_copy_(axis, dead, param.index_select(axis, src))
        opt.rows(name, dead, None)
        opt.rows(name, src, None)
    logit = torch.logit(split.clamp(1e-6, 1 - 1e-6)).clamp(*OPACITY_LOGIT_RANGE)
    model.opacity_logit[dead] = logit
    model.opacity_logit[src] = logit
    model.xyz[dead] += torch.randn(len(dead), 3, generator=gen) * model.log_scale[dead].exp() * 0.5
    return len(dead)


def copies_allowed(opacity: torch.Tensor, dead_opacity: float) -> torch.Tensor:
    """(N,) how many copies each Gaussian of `opacity` can give while its n + 1 shares (opacity
    1 − (1 − o)^(1/(n+1)) each) stay at 2·`dead_opacity` or more."""
    shares = torch.log1p(-opacity.double().clamp(max=1 - 1e-9)) / math.log1p(-2 * dead_opacity)
    return (shares.floor() - 1).clamp_min(0).long()


def _copy_rank(src: torch.Tensor) -> torch.Tensor:
    """For each entry of `src`, how many earlier entries name the same source (0 for the first)."""
    order = torch.argsort(src, stable=True)
    ordered = src[order]
    rank = torch.empty_like(src)
    rank[order] = torch.arange(len(src)) - torch.searchsorted(ordered, ordered)
    return rank


@torch.no_grad()
def sort(model: GOPModel, opt: Optimizer, accum: torch.Tensor, seed: int) -> None:
    """PLAS-sort the Gaussians on the model's grid (parameters, Adam state and the opacity accumulator alike)."""
    order = plas_order(sort_key(model), model.shape.grid_side, PLASConfig(seed=seed))
    opt.permute(order)
    accum.copy_(accum[:, order])


def track_opacities(accum: torch.Tensor, opacities: torch.Tensor, peak: bool = False) -> None:
    """Fold one iteration's drawn (deformed) opacities into `accum` ((2, N)): row 0 their running sum, or their
    running maximum when `peak`; row 1 how many iterations drew them."""
    if peak:
        torch.maximum(accum[0], opacities, out=accum[0])
    else:
        accum[0] += opacities
    accum[1] += 1


def opacity_level(accum: torch.Tensor, peak: bool = False) -> torch.Tensor:
    """(N,) each Gaussian's drawn opacity since `accum` was cleared (track_opacities): its mean, or its peak."""
    return accum[0].clone() if peak else accum[0] / accum[1].clamp_min(1)


@torch.no_grad()
def prune(model: GOPModel, accum: torch.Tensor, dead_opacity: float, peak: bool = False) -> int:
    """Park the slots whose drawn opacity (opacity_level: mean, or peak) since `accum` was cleared stayed below
    `dead_opacity`; returns how many.

    The stream cannot carry opacity 0 (its floor is sigmoid(-4)), so a parked slot gets the floor opacity
    and the smallest scale of the live Gaussians: a faint dot about a pixel wide that widens neither the
    opacity nor the scale range of the packed attributes.
    """
    dead = (opacity_level(accum, peak) < dead_opacity) & (accum[1] > 0)
    model.opacity_logit[dead] = OPACITY_LOGIT_RANGE[0]
    if not dead.all():
        model.log_scale[dead] = model.log_scale[~dead].amin(0)
    return int(dead.sum())
