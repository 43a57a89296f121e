"""The static layer of a layered scene (model format 2): Gaussians that never move, fitted once per scene.

It holds the five canonical attributes of a GOP model (X, S, Q, O, C) with the
same activations, and optionally a degree-1 view-dependent colour term
(`sh1`, the linear part of a spherical-harmonics colour):

    colour = relu(C) + Σ_k d_k · sh1[:, k, :]       d = unit vector from the camera to the mean

No temporal features and no deformation: frame i of GOP k draws these
Gaussians unchanged beside the deformed dynamic layer (stgs.model.renderer).
"""

from __future__ import annotations

import torch
from torch import nn

from stgs.model.gop import Gaussians, GOPModel, square_side

SH_DEGREES = (0, 1)
"""Degrees of view-dependent colour a static layer may carry (0: none)."""

STATIC_TENSORS = ("xyz", "log_scale", "rotation", "opacity_logit", "color")
"""The canonical attributes the static and the dynamic layers share (safetensors names)."""


class StaticLayer(nn.Module):
    """Canonical Gaussians drawn in every frame of the scene."""

    def __init__(self, capacity: int, sh_degree: int = 0):
        super().__init__()
        if sh_degree not in SH_DEGREES:
            raise ValueError(f"static layer: sh_degree must be one of {SH_DEGREES}, got {sh_degree}")
        self.capacity, self.sh_degree = capacity, sh_degree
        self.xyz = nn.Parameter(torch.zeros(capacity, 3))
        self.log_scale = nn.Parameter(torch.full((capacity, 3), -4.0))
        self.rotation = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(capacity, 1))
        self.opacity_logit = nn.Parameter(torch.full((capacity,), -10.0))
        self.color = nn.Parameter(torch.zeros(capacity, 3))
        if sh_degree:
            self.sh1 = nn.Parameter(torch.zeros(capacity, 3, 3))

    @property
    def grid_side(self) -> int:
        """S_s with capacity = S_s², or 0 when the capacity is not a square."""
        return square_side(self.capacity)

    def gaussians(self, camera_center: torch.Tensor) -> Gaussians:
        """The activated Gaussians as seen from `camera_center` (the centre matters only with sh1)."""
        color = torch.relu(self.color)
        if self.sh_degree:
            view = self.xyz - camera_center.to(self.xyz.dtype)
            view = view / torch.linalg.vector_norm(view, dim=1, keepdim=True).clamp_min(1e-12)
            color = color + torch.einsum("nk,nkc->nc", view, self.sh1)
        return Gaussians(self.xyz, self.rotation, torch.exp(self.log_scale), torch.sigmoid(self.opacity_logit),
                         color)

    @classmethod
    def from_canonical(cls, source: GOPModel | StaticLayer, sh_degree: int = 0,
                       sh1: torch.Tensor | None = None) -> StaticLayer:
        """A static layer of `sh_degree` holding the canonical attributes of a GOP model (the trainer fits the
        static layer as one) or of another static layer; sh1 starts at zero, or at `sh1` (degree 1)."""
        layer = cls(source.xyz.shape[0], 1 if sh1 is not None else sh_degree)
        with torch.no_grad():
            for name in STATIC_TENSORS:
                getattr(layer, name).copy_(getattr(source, name))
            if sh1 is not None:
                layer.sh1.copy_(sh1)
        return layer


def merge(static: Gaussians, dynamic: Gaussians) -> Gaussians:
    """One set of Gaussians for one `rasterize` call (the splatter sorts both layers by depth together)."""
    return Gaussians(*(torch.cat([getattr(static, k), getattr(dynamic, k)])
                       for k in ("means", "quats", "scales", "opacities", "colors")))
