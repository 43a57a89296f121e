"""ctypes bindings of the native splatter (stgs/native/csrc/splat.cpp) and its autograd glue."""

from __future__ import annotations

import ctypes
from ctypes import c_int, c_int64, c_void_p

import torch

from stgs.native.build import load
from stgs.render.project import Projected

_CONFIGURED: set[int] = set()


def library() -> ctypes.CDLL:
    lib = load()
    if id(lib) not in _CONFIGURED:
        lib.stgs_project.argtypes = [c_int64] + [c_void_p] * 10 + [c_int]
        lib.stgs_project.restype = None
        lib.stgs_raster_forward.argtypes = [c_int64] + [c_void_p] * 7 + [c_int, c_int, c_void_p, c_int, c_int]
        lib.stgs_raster_forward.restype = c_void_p
        lib.stgs_raster_backward.argtypes = [c_void_p, c_int64] + [c_void_p] * 7 + [c_int]
        lib.stgs_raster_backward.restype = None
        lib.stgs_raster_pairs.argtypes = [c_void_p]
        lib.stgs_raster_pairs.restype = c_int64
        lib.stgs_raster_free.argtypes = [c_void_p]
        lib.stgs_raster_free.restype = None
        _CONFIGURED.add(id(lib))
    return lib


def ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


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
    library().stgs_project(n, ptr(means), ptr(quats), ptr(scales), ptr(opacities), ptr(view),
                           ptr(intr), ptr(out.means2d), ptr(out.conics), ptr(out.depths),
                           ptr(out.extents), torch.get_num_threads())
    return out


class RasterHandle:
    """Owns the binning the forward pass left for the backward pass."""

    def __init__(self, handle: int):
        self.handle = handle

    def pairs(self) -> int:
        return library().stgs_raster_pairs(self.handle)

    def __del__(self) -> None:
        if self.handle:
            library().stgs_raster_free(self.handle)
            self.handle = 0


def raster_forward(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                   colors: torch.Tensor, background: torch.Tensor, depths: torch.Tensor,
                   extents: torch.Tensor, width: int, height: int, for_backward: bool = False
                   ) -> tuple[torch.Tensor, RasterHandle]:
    """Native compositing of float32 contiguous inputs; returns the image and its handle (which the
    backward pass can use only when `for_backward`)."""
    out = torch.empty(height, width, 3)
    handle = library().stgs_raster_forward(
        means2d.shape[0], ptr(means2d), ptr(conics), ptr(opacities), ptr(colors), ptr(depths),
        ptr(extents), ptr(background), width, height, ptr(out), int(for_backward), torch.get_num_threads())
    return out, RasterHandle(handle)


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
        library().stgs_raster_backward(ctx.handle.handle, n, ptr(background), ptr(grad_out),
                                       *(ptr(g) for g in grads), torch.get_num_threads())
        return (*grads, None, None, None, None)
