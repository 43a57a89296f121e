"""The native splatter's stages from Python (typed by csrc/stgs_abi.h through stgs.native.abi) and its autograd
glue: projection, binning alone, forward (with its per-pixel bookkeeping), backward."""

from __future__ import annotations

from typing import Any

import torch

from stgs.native.abi import ptr
from stgs.native.library import load
from stgs.render.project import Projected
from stgs.render.stages import TILE, Bins


def f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


def project_native(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                   opacities: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> Projected:
    """Projection in C++ (double precision inside, float32 out); not differentiable."""
    n = means.shape[0]
    means, quats, scales, opacities = f32(means), f32(quats), f32(scales), f32(opacities)
    view = viewmat.detach().to(torch.float64).contiguous()
    intr = K.detach().to(torch.float64).contiguous()
    out = Projected(torch.empty(n, 2), torch.empty(n, 3), torch.empty(n), torch.empty(n, 2))
    load().stgs_project(n, ptr(means), ptr(quats), ptr(scales), ptr(opacities), ptr(view), ptr(intr),
                        ptr(out.means2d), ptr(out.conics), ptr(out.depths), ptr(out.extents),
                        torch.get_num_threads())
    return out


class NativeProjection(torch.autograd.Function):
    """project_native with its gradient (csrc/project.cpp's stgs_project_backward): means2d and conics
    differentiable in means, quats and scales; depths and extents are constants, as in the torch projection.
    Faster than autograd through the float64 torch twin (bench.training.loss_terms; docs/BENCHMARKS.md, "Training
    steps")."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K):
        proj = project_native(means, quats, scales, opacities, viewmat, K)
        ctx.save_for_backward(f32(means), f32(quats), f32(scales))
        ctx.camera = viewmat.detach().to(torch.float64).contiguous(), K.detach().to(torch.float64).contiguous()
        ctx.mark_non_differentiable(proj.depths, proj.extents)
        return proj.means2d, proj.conics, proj.depths, proj.extents

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, _depths, _extents):
        means, quats, scales = ctx.saved_tensors
        view, intr = ctx.camera
        n = means.shape[0]
        grads = torch.empty(n, 3), torch.empty(n, 4), torch.empty(n, 3)
        grad_means2d, grad_conics = f32(grad_means2d), f32(grad_conics)  # held through the call
        load().stgs_project_backward(n, ptr(means), ptr(quats), ptr(scales), ptr(view), ptr(intr), ptr(grad_means2d),
                                     ptr(grad_conics), *(ptr(g) for g in grads), torch.get_num_threads())
        return *grads, None, None, None


def project_trainable(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      viewmat: torch.Tensor, K: torch.Tensor) -> Projected:
    """The native projection of float32 Gaussians, differentiable in means, quats and scales (NativeProjection)."""
    return Projected(*NativeProjection.apply(means, quats, scales, opacities, viewmat, K))


class RasterHandle:
    """Owns the native context a binning or forward pass left (its tile lists; after a forward for the
    backward pass, the per-pixel bookkeeping too)."""

    def __init__(self, handle: Any, width: int, height: int):
        self.handle, self.width, self.height = handle, width, height

    def pairs(self) -> int:
        return load().stgs_raster_pairs(self.handle)

    def bins(self) -> Bins:
        """The tile lists (stage 2's output)."""
        tiles_x, tiles_y = -(-self.width // TILE), -(-self.height // TILE)
        tile_start = torch.empty(tiles_x * tiles_y + 1, dtype=torch.int64)
        ids = torch.empty(self.pairs(), dtype=torch.int32)
        load().stgs_raster_tiles(self.handle, ptr(tile_start), ptr(ids))
        return Bins(tile_start, ids, tiles_x, tiles_y)

    def pixels(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(final transmittance, 1-based rank of the last contributor) per pixel, of a for_backward forward."""
        trans_final = torch.full((self.height, self.width), float("nan"))
        n_contrib = torch.full((self.height, self.width), -1, dtype=torch.int32)
        load().stgs_raster_pixels(self.handle, ptr(trans_final), ptr(n_contrib))
        return trans_final, n_contrib

    def __del__(self) -> None:
        if self.handle is not None:
            load().stgs_raster_free(self.handle)
            self.handle = None


def bin_native(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, depths: torch.Tensor,
               extents: torch.Tensor, width: int, height: int) -> RasterHandle:
    """Stage 2 alone on float32 contiguous inputs: a handle whose `bins()` are the tile lists."""
    handle = load().stgs_raster_bin(means2d.shape[0], ptr(means2d), ptr(conics), ptr(opacities), ptr(depths),
                                    ptr(extents), width, height, torch.get_num_threads())
    return RasterHandle(handle, width, height)


def raster_forward(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                   colors: torch.Tensor, background: torch.Tensor, depths: torch.Tensor,
                   extents: torch.Tensor, width: int, height: int, for_backward: bool = False
                   ) -> tuple[torch.Tensor, RasterHandle]:
    """Native compositing of float32 contiguous inputs; returns the image and its handle (which the
    backward pass can use only when `for_backward`)."""
    out = torch.empty(height, width, 3)
    handle = load().stgs_raster_forward(
        means2d.shape[0], ptr(means2d), ptr(conics), ptr(opacities), ptr(colors), ptr(depths),
        ptr(extents), ptr(background), width, height, ptr(out), int(for_backward), torch.get_num_threads())
    return out, RasterHandle(handle, width, height)


class NativeComposite(torch.autograd.Function):
    """Native compositing with a native backward pass to means2d, conics, opacities, colours, background."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, depths, extents, width,
                height):
        inputs = [f32(t) for t in (means2d, conics, opacities, colors, background)]
        out, handle = raster_forward(*inputs, f32(depths), f32(extents), width, height, for_backward=True)
        ctx.handle = handle  # holds its own copy of every Gaussian input the backward reads
        ctx.num_gaussians = means2d.shape[0]
        ctx.save_for_backward(inputs[4])
        return out

    @staticmethod
    def backward(ctx, grad_out):
        (background,) = ctx.saved_tensors
        n = ctx.num_gaussians
        grads = [torch.zeros(n, 2), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, 3), torch.zeros(3)]
        grad_out = f32(grad_out)
        load().stgs_raster_backward(ctx.handle.handle, n, ptr(background), ptr(grad_out),
                                    *(ptr(g) for g in grads), torch.get_num_threads())
        return (*grads, None, None, None, None)
