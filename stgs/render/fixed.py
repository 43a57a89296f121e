"""Splatting moving Gaussians over a layer that does not move, from a camera that does not move.

A layered scene (model format 2, docs/MODEL_FORMAT.md) draws its static layer and the deformed dynamic layer in one
`rasterize` call per frame. While the camera stays put, the static layer's projection and tile lists are the
same every frame, and so is every tile that no dynamic Gaussian reaches: its list is the same static
Gaussians in the same depth order, so compositing it again gives the same pixels. `FixedLayerView` projects,
bins and renders the static layer alone once (csrc/kept.cpp); each frame then projects and bins only the
dynamic Gaussians, merges each reached tile's two lists front to back (equal depths in the order a bin of
both would give them) and composites only those tiles, copying the others from the kept image. The image is
bit for bit the one `rasterize` makes of both layers, the static layer first (tests/render/test_fixed.py);
the saving follows the static layer's share of the binning and of the tiles (docs/BENCHMARKS.md, "Real-time
playback"). Native float32 CPU only. With moving Gaussians that need gradients (training over a frozen
layer: a layered scene's GOP stage), `draw` is differentiable in them. The tiles they reach are composited as the
differentiable `rasterize` of both layers composites them (its tracked kernel, bit for bit); the others are
copied from the kept image (the inference kernel: float32 rounding apart) and carry no gradient for them, so
the backward pass visits only the reached tiles and its gradients are those of one composite of both layers
(the background and the kept layer get none).
"""

from __future__ import annotations

import threading

import torch

from stgs.native.abi import ptr
from stgs.native.library import load
from stgs.render import _check_inputs, needs_grad
from stgs.render.native import RasterHandle, f32, project_native, project_trainable


class FixedLayerView:
    """The static Gaussians (means, quats, scales, opacities, colors as `rasterize` takes them) seen from one
    camera (viewmat, K, width, height) over one background: their projection, tile lists and image alone,
    kept in a native context."""

    def __init__(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                 colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                 background: torch.Tensor | None = None):
        self._kept = None
        background = torch.zeros(3) if background is None else background
        _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background)
        if means.dtype != torch.float32 or means.device.type != "cpu":
            raise ValueError("FixedLayerView takes float32 CPU tensors (the native splatter's inference path)")
        if needs_grad(means, quats, scales, opacities, colors, background):
            raise ValueError("FixedLayerView is for inference: its inputs must not require gradients")
        self.viewmat, self.K = viewmat.detach().clone(), K.detach().clone()
        self.width, self.height = width, height
        self.background = f32(background)
        self.count = means.shape[0]
        p = project_native(means, quats, scales, opacities, self.viewmat, self.K)
        self.image = torch.empty(height, width, 3)
        """The kept layer alone."""
        self._kept = load().stgs_raster_keep(
            self.count, ptr(p.means2d), ptr(p.conics), ptr(f32(opacities)), ptr(f32(colors)), ptr(p.depths),
            ptr(p.extents), ptr(self.background), width, height, ptr(self.image), torch.get_num_threads())
        self._lock = threading.Lock()  # the context holds the merged lists of the frame being drawn
        self.last_reused_tiles = 0
        """Tiles the last `draw` copied from the kept image instead of compositing."""

    def draw(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
             colors: torch.Tensor) -> torch.Tensor:
        """(H, W, 3) float32 image of the kept layer with these moving Gaussians, as `rasterize` of both
        (the kept layer first) from the kept camera over the kept background; differentiable in the moving
        Gaussians when they need gradients."""
        _check_inputs(means, quats, scales, opacities, colors, self.viewmat, self.K, self.width, self.height,
                      self.background)
        if means.dtype != torch.float32:
            raise ValueError("FixedLayerView.draw takes float32 Gaussians")
        if needs_grad(means, quats, scales, opacities, colors):
            p = project_trainable(means, quats, scales, opacities, self.viewmat, self.K)
            return OverKeptLayer.apply(self, p.means2d, p.conics, opacities, colors, p.depths, p.extents)
        p = project_native(means, quats, scales, opacities, self.viewmat, self.K)
        out = torch.empty(self.height, self.width, 3)
        opacities, colors = f32(opacities), f32(colors)
        with self._lock:
            self.last_reused_tiles = load().stgs_raster_over(
                self._kept, means.shape[0], ptr(p.means2d), ptr(p.conics), ptr(opacities), ptr(colors),
                ptr(p.depths), ptr(p.extents), ptr(out), torch.get_num_threads())
        return out

    def __del__(self) -> None:
        if self._kept is not None:
            load().stgs_raster_kept_free(self._kept)
            self._kept = None


class OverKeptLayer(torch.autograd.Function):
    """A kept layer's image with moving Gaussians (projected, float32) over it, and their gradients."""

    @staticmethod
    def forward(ctx, layer: FixedLayerView, means2d, conics, opacities, colors, depths, extents):
        inputs = [f32(t) for t in (means2d, conics, opacities, colors, depths, extents)]
        out = torch.empty(layer.height, layer.width, 3)
        handle = load().stgs_raster_over_train(layer._kept, means2d.shape[0], *(ptr(t) for t in inputs), ptr(out),
                                               torch.get_num_threads())
        ctx.handle = RasterHandle(handle, layer.width, layer.height)  # holds the inputs the backward reads
        ctx.kept, ctx.moving, ctx.background = layer.count, means2d.shape[0], layer.background
        return out

    @staticmethod
    def backward(ctx, grad_out):
        n = ctx.kept + ctx.moving
        grads = [torch.zeros(n, 2), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, 3)]
        grad_out, grad_background = f32(grad_out), torch.zeros(3)  # held: the call writes and reads them
        load().stgs_raster_backward(ctx.handle.handle, n, ptr(ctx.background), ptr(grad_out),
                                    *(ptr(g) for g in grads), ptr(grad_background), torch.get_num_threads())
        return (None, *(g[ctx.kept:] for g in grads), None, None)
