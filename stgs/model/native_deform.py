"""Native (C++) evaluation of GOPModel.deform for inference.

The torch `GOPModel.deform` is the oracle; this path evaluates every MLP layer
per block of 32 Gaussians while the block sits in cache, and (given a camera)
skips the view-dependent decoders of Gaussians that cannot reach the image.
"""

from __future__ import annotations

import ctypes
from ctypes import c_int, c_int64, c_void_p

import torch

from stgs.model.gop import (
    FEATURE_DIM,
    HIDDEN,
    Gaussians,
    GOPModel,
    frame_time,
    positional_encoding,
)
from stgs.native.build import load

MAX_WINDOW = 8
"""Largest sliding window the native kernel accepts."""

_CONFIGURED: set[int] = set()


def _library() -> ctypes.CDLL:
    lib = load()
    if id(lib) not in _CONFIGURED:
        lib.stgs_deform.argtypes = ([c_int64, c_int, c_int] + [c_void_p] * 15
                                    + [c_int, c_int] + [c_void_p] * 5 + [c_int])
        lib.stgs_deform.restype = None
        _CONFIGURED.add(id(lib))
    return lib


def _c(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


OUT_WIDTH = 16
"""Padded output width of the packed second layers."""


def _pack_second(first: torch.Tensor, second: torch.Tensor, col0: int,
                 col1: int) -> torch.Tensor:
    """(128, 16) block-diagonal second layer: hidden[:64] -> cols [0, col0), hidden[64:] -> [col0, col1)."""
    packed = torch.zeros(2 * HIDDEN, OUT_WIDTH)
    packed[:HIDDEN, :col0] = first.T
    packed[HIDDEN:, col0:col1] = second.T
    return packed.contiguous()


class PackedWeights:
    """The deformation field's weights arranged for the kernel (in x out, decoders side by side)."""

    def __init__(self, model: GOPModel):
        field = model.field
        in_feat = model.shape.window * FEATURE_DIM
        temporal = _c(field.temporal.weight)
        self.temporal_feat = temporal[:, :in_feat].T.contiguous()
        self.temporal_pe = temporal[:, in_feat:]
        self.geo1 = torch.cat([_c(field.d_pos[0].weight), _c(field.d_cov[0].weight)], 0).T.contiguous()
        self.geo2 = _pack_second(_c(field.d_pos[2].weight), _c(field.d_cov[2].weight), 3, 10)
        self.app1 = torch.cat([_c(field.d_opacity[0].weight), _c(field.d_color[0].weight)],
                              0).T.contiguous()
        self.app2 = _pack_second(_c(field.d_opacity[2].weight), _c(field.d_color[2].weight), 1, 4)

    def pe_bias(self, frame: int, model: GOPModel) -> torch.Tensor:
        """The γ(t) part of D_t's input, folded into a per-frame bias."""
        pe = positional_encoding(frame_time(frame, model.shape.gop_size), model.shape.pe_freqs)
        return (self.temporal_pe @ pe).contiguous()


def deform_native(model: GOPModel, frame: int, camera_center: torch.Tensor,
                  weights: PackedWeights | None = None, viewmat: torch.Tensor | None = None,
                  K: torch.Tensor | None = None, width: int = 0, height: int = 0) -> Gaussians:
    """GOPModel.deform in C++ (float32, no autograd).

    With viewmat/K/width/height, Gaussians that cannot put alpha >= 1/255 on
    the image get opacity 0 (the splatter would skip them anyway).
    """
    model.check_frame(frame)
    if model.shape.window > MAX_WINDOW:
        raise ValueError(f"native deform supports windows up to {MAX_WINDOW}")
    weights = weights or PackedWeights(model)
    n = model.shape.capacity
    feats = _c(model.features)
    canon = [_c(t) for t in (model.xyz, model.log_scale, model.rotation, model.opacity_logit,
                             model.color)]
    center = _c(camera_center.reshape(3))
    pe_bias = weights.pe_bias(frame, model)
    out = Gaussians(torch.empty(n, 3), torch.empty(n, 4), torch.empty(n, 3), torch.empty(n),
                    torch.empty(n, 3))
    view_ptr = k_ptr = None
    if viewmat is not None:
        view = viewmat.detach().to(torch.float64).contiguous()
        intr = K.detach().to(torch.float64).contiguous()
        view_ptr, k_ptr = view.data_ptr(), intr.data_ptr()
    _library().stgs_deform(
        n, model.shape.window, frame, feats.data_ptr(), *(t.data_ptr() for t in canon),
        weights.temporal_feat.data_ptr(), pe_bias.data_ptr(), weights.geo1.data_ptr(),
        weights.geo2.data_ptr(), weights.app1.data_ptr(), weights.app2.data_ptr(),
        center.data_ptr(), view_ptr, k_ptr,
        width, height, out.means.data_ptr(), out.quats.data_ptr(), out.scales.data_ptr(),
        out.opacities.data_ptr(), out.colors.data_ptr(), torch.get_num_threads())
    return out
