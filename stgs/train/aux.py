"""The transformer-guided auxiliary pass (paper §Temporal features, appendix).

For each Gaussian the W window features e_i … e_{i+W-1}, each joined with
γ(t) and γ(X), form a sequence of W tokens; two `nn.TransformerEncoderLayer`
(2 heads, feed-forward 64, tanh) encode it; the mean token, projected to 64
and squashed by tanh, is an alternative hidden state. Decoded by the same
decoders it renders an auxiliary image (0.2·SSIM loss against the target),
and it teaches D_t's hidden state by self-distillation (weight 0.005). Only
training uses it: nothing of it is packed or streamed.
"""

from __future__ import annotations

import torch
from torch import nn

from stgs.model.gop import FEATURE_DIM, HIDDEN, GOPModel, frame_time, positional_encoding

POSITION_FREQS = 4
"""Frequencies of γ(X) per coordinate."""


class AuxTransformer(nn.Module):
    def __init__(self, pe_freqs: int, heads: int = 2, feedforward: int = 64, layers: int = 2):
        super().__init__()
        self.pe_freqs = pe_freqs
        d_model = FEATURE_DIM + 2 * pe_freqs + 6 * POSITION_FREQS
        d_model += d_model % heads
        self.d_model = d_model
        self.encoder = nn.ModuleList(
            nn.TransformerEncoderLayer(d_model, heads, dim_feedforward=feedforward, dropout=0.0,
                                       activation=torch.tanh, batch_first=True) for _ in range(layers))
        self.out = nn.Linear(d_model, HIDDEN, bias=False)

    def tokens(self, model: GOPModel, frame: int, window: torch.Tensor) -> torch.Tensor:
        """(N, W, d_model) tokens from the (N, W·16) window features of `frame` (as the MLP sees them)."""
        n, w = window.shape[0], model.shape.window
        pe_t = positional_encoding(frame_time(frame, model.shape.gop_size), self.pe_freqs, window.dtype)
        pe_x = positional_encoding(model.xyz.detach(), POSITION_FREQS, window.dtype).reshape(n, -1)
        parts = [window.reshape(n, w, FEATURE_DIM), pe_t.expand(n, w, -1), pe_x[:, None].expand(n, w, -1)]
        pad = self.d_model - sum(p.shape[-1] for p in parts)
        if pad:
            parts.append(window.new_zeros(n, w, pad))
        return torch.cat(parts, dim=-1)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """(R, W, d_model) -> (R, 64) hidden state."""
        x = tokens
        for layer in self.encoder:
            x = layer(x)
        return torch.tanh(self.out(x.mean(dim=1)))
