"""One GOP of a StreamSTGS model: canonical Gaussians, temporal features, deformation field.

Per frame i (0-based) of a GOP of G frames the deformation field reads the
features e_i ... e_{i+W-1} of every Gaussian and a positional encoding of
t = i / (G - 1), and returns offsets to the canonical attributes (docs/MODEL_FORMAT.md):

    means = X + ΔX            scales = exp(S + ΔS)        quats = Q + ΔQ
    opacity = clamp(sigmoid(O) + ΔO, 0, 1)                colours = relu(C) + ΔC

ΔO = tanh(·) is added after the sigmoid, so a Gaussian can fade in and out
completely within a GOP (see docs/MODEL_FORMAT.md for this reading of the paper).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

FEATURE_DIM = 16
"""Channels of one temporal feature e_i per Gaussian."""
HIDDEN = 64
"""Width of the temporal MLP output and of every decoder's hidden layer."""


@dataclass(frozen=True)
class GOPShape:
    """Sizes that fix every tensor of a GOP model."""

    capacity: int
    """Gaussian slots N = S² (unused slots carry opacity 0)."""
    gop_size: int = 60
    """Frames G in the GOP."""
    window: int = 3
    """Sliding window W of temporal features read per frame."""
    pe_freqs: int = 4
    """Frequencies L of the positional encoding γ(t) (2L values)."""

    @property
    def num_features(self) -> int:
        """E = G + W - 1 temporal features."""
        return self.gop_size + self.window - 1

    @property
    def grid_side(self) -> int:
        """S with N = S², or 0 when the capacity is not a square."""
        return square_side(self.capacity)


def square_side(capacity: int) -> int:
    """S with capacity = S² (a PLAS grid's side), or 0 when the capacity is not a positive square."""
    side = math.isqrt(capacity) if capacity > 0 else 0
    return side if side * side == capacity else 0


@dataclass
class Gaussians:
    """Activated Gaussians ready for the splatter (the rasterize contract)."""

    means: torch.Tensor
    """(N, 3) world positions."""
    quats: torch.Tensor
    """(N, 4) wxyz, any norm (the splatter normalises)."""
    scales: torch.Tensor
    """(N, 3) linear scales."""
    opacities: torch.Tensor
    """(N,) in [0, 1]."""
    colors: torch.Tensor
    """(N, 3) RGB."""


def positional_encoding(t: float | torch.Tensor, freqs: int,
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """γ(t) = (sin(2^k π t), cos(2^k π t)) for k < freqs: (2·freqs,) for a scalar t, (R, 2·freqs) for (R,)."""
    t = torch.as_tensor(t, dtype=dtype)
    angles = (2.0 ** torch.arange(freqs, dtype=dtype)) * math.pi * t[..., None]
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


def frame_time(frame: int, gop_size: int) -> float:
    """t of frame i normalised to [0, 1] inside the GOP."""
    return frame / (gop_size - 1) if gop_size > 1 else 0.0


def _decoder(in_dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, HIDDEN, bias=False), nn.ReLU(),
                         nn.Linear(HIDDEN, out_dim, bias=False))


class DeformationField(nn.Module):
    """Temporal MLP D_t and the decoders D_v, D_cov, D_o, D_c of the paper's appendix (no biases)."""

    def __init__(self, window: int, pe_freqs: int):
        super().__init__()
        self.window = window
        self.pe_freqs = pe_freqs
        self.temporal = nn.Linear(window * FEATURE_DIM + 2 * pe_freqs, HIDDEN, bias=False)
        self.d_pos = _decoder(HIDDEN, 3)
        self.d_cov = _decoder(HIDDEN, 7)
        self.d_opacity = _decoder(HIDDEN + 3, 1)
        self.d_color = _decoder(HIDDEN + 3, 3)

    def hidden(self, window_feats: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """h = tanh(D_t(concat(e_i … e_{i+W-1}, γ(t)))) for window_feats (R, W·16), t scalar or (R,)."""
        pe = positional_encoding(t, self.pe_freqs, window_feats.dtype)
        x = torch.cat([window_feats, pe.expand(window_feats.shape[0], -1)], dim=1)
        return torch.tanh(self.temporal(x))

    def forward(self, window_feats: torch.Tensor, t: float | torch.Tensor, means: torch.Tensor,
                camera_center: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Offsets (ΔX, ΔS, ΔQ, ΔO, ΔC) for canonical means (R, 3) seen from camera_center ((3,) or (R, 3))."""
        return self.decode(self.hidden(window_feats, t), means, camera_center)

    def decode(self, h: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The decoders D_v, D_cov, D_o, D_c applied to a hidden state h (R, 64)."""
        d_x = self.d_pos(h)
        cov = self.d_cov(h)
        view = means + d_x - camera_center.to(means.dtype)
        view = view / torch.linalg.vector_norm(view, dim=1, keepdim=True).clamp_min(1e-12)
        hv = torch.cat([h, view], dim=1)
        d_o = torch.tanh(self.d_opacity(hv)).squeeze(1)
        return d_x, cov[:, :3], cov[:, 3:], d_o, self.d_color(hv)


def flat_window(block: torch.Tensor) -> torch.Tensor:
    """(N, W·16) per-Gaussian concatenation of a (W, N, 16) block of feature frames."""
    return block.permute(1, 0, 2).reshape(block.shape[1], -1)


class GOPModel(nn.Module):
    """Canonical Gaussians + temporal features + deformation field of one GOP."""

    def __init__(self, shape: GOPShape, features: bool = True):
        """features=False: the model holds no temporal features (an empty (0, N, 16) tensor), for a caller that
        sets them itself or streams them frame by frame (feature_window)."""
        super().__init__()
        self.shape = shape
        n = shape.capacity
        self.xyz = nn.Parameter(torch.zeros(n, 3))
        self.log_scale = nn.Parameter(torch.full((n, 3), -4.0))
        self.rotation = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))
        self.opacity_logit = nn.Parameter(torch.full((n,), -10.0))
        self.color = nn.Parameter(torch.zeros(n, 3))
        self.features = nn.Parameter(torch.zeros(shape.num_features if features else 0, n, FEATURE_DIM))
        self.field = DeformationField(shape.window, shape.pe_freqs)

    def feature_window(self, frame: int, window: list[torch.Tensor] | None = None) -> list[torch.Tensor]:
        """The W feature frames e_frame … e_{frame+W-1}, (N, 16) float32 contiguous each: `window` checked, or
        slices of self.features when None."""
        self.check_frame(frame)
        w, n = self.shape.window, self.shape.capacity
        if window is None:
            if self.features.shape[0] != self.shape.num_features:
                raise ValueError("this GOP model holds no features (streamed): pass the frame's feature window")
            feats = self.features.detach().to(torch.float32).contiguous()
            return [feats[frame + j] for j in range(w)]
        if len(window) != w or any(f.shape != (n, FEATURE_DIM) or f.dtype != torch.float32
                                   or not f.is_contiguous() for f in window):
            raise ValueError(f"a feature window is {w} contiguous float32 ({n}, {FEATURE_DIM}) frames")
        return window

    def window_features(self, frame: int, window: list[torch.Tensor] | None = None) -> torch.Tensor:
        """(N, W·16) concatenation of e_frame … e_{frame+W-1} (from `window` when given, see feature_window)."""
        if window is not None:
            return torch.cat(self.feature_window(frame, window), dim=1)
        return flat_window(self.feature_block(frame))

    def feature_block(self, frame: int) -> torch.Tensor:
        """(W, N, 16) the slice e_frame … e_{frame+W-1} of self.features (one view: one gradient buffer for every
        term that reads it)."""
        self.check_frame(frame)
        return self.features[frame:frame + self.shape.window]

    def check_frame(self, frame: int) -> None:
        if not 0 <= frame < self.shape.gop_size:
            raise ValueError(f"frame {frame} is outside the GOP (0..{self.shape.gop_size - 1})")

    def canonical(self) -> Gaussians:
        """The canonical Gaussians, activated (docs/MODEL_FORMAT.md), with no deformation."""
        return Gaussians(self.xyz, self.rotation, torch.exp(self.log_scale),
                         torch.sigmoid(self.opacity_logit), torch.relu(self.color))

    def deform(self, frame: int, camera_center: torch.Tensor, window: list[torch.Tensor] | None = None) -> Gaussians:
        """The Gaussians of GOP frame `frame` as seen from `camera_center` (pure torch); `window` as in
        feature_window."""
        t = frame_time(frame, self.shape.gop_size)
        return self.apply_offsets(self.field(self.window_features(frame, window), t, self.xyz, camera_center))

    def apply_offsets(self, offsets: tuple[torch.Tensor, ...]) -> Gaussians:
        """Canonical Gaussians + the field's offsets (ΔX, ΔS, ΔQ, ΔO, ΔC), activated (docs/MODEL_FORMAT.md)."""
        d_x, d_s, d_q, d_o, d_c = offsets
        opacity = (torch.sigmoid(self.opacity_logit) + d_o).clamp(0.0, 1.0)
        return Gaussians(self.xyz + d_x, self.rotation + d_q, torch.exp(self.log_scale + d_s),
                         opacity, torch.relu(self.color) + d_c)
