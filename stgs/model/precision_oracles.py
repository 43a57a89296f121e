"""Pure-torch oracles of the native deformation's reduced precisions (stgs.model.native_deform): each rounds
what its kernel rounds, so a test can hold the kernel to it within float32 rounding, and the oracle to the
float32 deformation within the precision's own error."""

from __future__ import annotations

import torch

from stgs.model.gop import FEATURE_DIM, Gaussians, GOPModel, frame_time, positional_encoding
from stgs.model.native_deform import Int16Layer, PackedWeights


def _bf16(t: torch.Tensor | torch.nn.Module) -> torch.Tensor:
    assert isinstance(t, torch.Tensor)  # a layer's `weight` types as either
    return t.detach().to(torch.bfloat16).to(torch.float32)


def deform_bf16_reference(model: GOPModel, frame: int, camera_center: torch.Tensor) -> Gaussians:
    """Pure-torch oracle of the bf16 kernel: every layer input and weight rounded to bf16, products and
    sums in float32, γ(t)'s share of D_t in float32 (the kernel folds it into a bias)."""
    field, shape = model.field, model.shape
    in_feat = shape.window * FEATURE_DIM
    temporal = field.temporal.weight.detach()
    pe = positional_encoding(frame_time(frame, shape.gop_size), shape.pe_freqs)
    h = _bf16(torch.tanh(_bf16(model.window_features(frame)) @ _bf16(temporal[:, :in_feat]).T
                         + temporal[:, in_feat:] @ pe))

    def decoder(layers: torch.nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        return _bf16(torch.relu(x @ _bf16(layers[0].weight).T)) @ _bf16(layers[2].weight).T

    d_x, cov = decoder(field.d_pos, h), decoder(field.d_cov, h)
    view = model.xyz.detach() + d_x - camera_center.reshape(1, 3).float()
    view = view / torch.linalg.vector_norm(view, dim=1, keepdim=True).clamp_min(1e-12)
    hv = torch.cat([h, _bf16(view)], dim=1)
    d_o = torch.tanh(decoder(field.d_opacity, hv)).squeeze(1)
    return model.apply_offsets((d_x, cov[:, :3], cov[:, 3:], d_o, decoder(field.d_color, hv)))


def _quantised_rows(x: torch.Tensor, q: float, unit: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The int16 kernel's row quantisation: integers rint(x · (q / m)) and row scales m / q, with m the row's
    max |x|, or 1 for a `unit` layer (inputs within [-1, 1] by construction); a row with NaN (or, scaled by
    its max, Inf) gets zeros and scale NaN."""
    peak = x.abs().amax(1)
    if unit:
        bad = torch.isnan(x).any(1)
        ints = torch.where(bad[:, None], 0.0, (x * q).round())
        return ints, torch.where(bad, float("nan"), torch.full_like(peak, 1.0) / q)
    bad = ~torch.isfinite(peak)
    inv = torch.where(peak > 0, q / peak, torch.zeros_like(peak))
    ints = torch.where(bad[:, None], 0.0, (x * inv[:, None]).round())
    return ints, torch.where(bad, float("nan"), peak / q)


def _int16_product(x: torch.Tensor, layer: Int16Layer, unit: bool = False) -> torch.Tensor:
    """x @ the layer as the kernel computes it: exact integer sums (float64 holds them), then scaled."""
    ints, scale = _quantised_rows(x, layer.q, unit)
    weight = layer.weight.permute(0, 2, 1).reshape(-1, layer.weight.shape[1]).double()
    ints = torch.nn.functional.pad(ints.double(), (0, weight.shape[0] - ints.shape[1]))
    return (ints @ weight).float() * (scale[:, None] * layer.col_scale)


def deform_int16_reference(model: GOPModel, frame: int, camera_center: torch.Tensor) -> Gaussians:
    """Pure-torch oracle of the int16 kernel: every layer's input rows and weight columns quantised as the
    kernel does (PackedWeights.int16; the first decoder layers' inputs, tanh outputs and view directions,
    by the unit scale), γ(t)'s share of D_t in float32 as a bias."""
    weights = PackedWeights(model)
    temporal, geo1, geo2, app1, app2 = weights.int16()
    h = torch.tanh(_int16_product(model.window_features(frame).float(), temporal) + weights.pe_bias(frame, model))
    geo = _int16_product(torch.relu(_int16_product(h, geo1, unit=True)), geo2)
    d_x = geo[:, :3]
    view = model.xyz.detach() + d_x - camera_center.reshape(1, 3).float()
    view = view / torch.linalg.vector_norm(view, dim=1, keepdim=True).clamp_min(1e-12)
    app = _int16_product(torch.relu(_int16_product(torch.cat([h, view], dim=1), app1, unit=True)), app2)
    return model.apply_offsets((d_x, geo[:, 3:6], geo[:, 6:10], torch.tanh(app[:, 0]), app[:, 1:4]))
