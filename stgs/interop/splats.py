"""Gaussians as the 3DGS file formats hold them, and the exact way between them and our static layer.

`Splats` is the one form every reader returns and every writer takes: the 3DGS parameterisation of the INRIA
PLY (log scales, opacity logits, wxyz rotations as stored, spherical-harmonics coefficients with the DC term
first), float32, in our world frame (OpenCV axes, the cameras' frame). Formats that store activated values (glTF)
or quantise (SPZ) convert at their own edge.

Float32 values do not survive a change of parameterisation unchanged (C = 0.5 + Y_0·dc cannot give every float32
C, nor exp every scale). Where we convert, the stored value is the canonical preimage (`preimage`): the float32
nearest the exact inverse among those the forward map sends back to the value itself, when one exists. So a file
we write, read back into a static layer and written again has the same bytes.

A frame we export is put in canonical form first (`Splats.canonical`: unit rotations, log-scales and logits that
are the canonical preimages of their scales and opacities), the form a file of activated values (glTF) reads back
to. So an exported frame reads back from every lossless format to the same float32 values, on any CPU, rather
than to values one rounding away that render alike only where the float32 arithmetic happens to agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from stgs.errors import StgsError
from stgs.interop import sh as harmonics
from stgs.model.gop import Gaussians
from stgs.model.static import StaticLayer

MAX_SPLATS = 1 << 24
"""Most Gaussians a file may hold (16 M); checked against a header before anything is allocated."""
LOGIT_LIMIT = 104.0
"""Opacity logits are kept within ±this: sigmoid rounds to exactly 0 or 1 in float32 well inside it."""


class InteropError(StgsError):
    """A splat file that cannot be read or written as asked (one line, naming the file and what is wrong)."""


@dataclass
class Splats:
    """Gaussians in the 3DGS parameterisation, float32 numpy arrays, N of them."""

    means: np.ndarray
    """(N, 3) positions."""
    log_scales: np.ndarray
    """(N, 3) natural logs of the scales."""
    quats: np.ndarray
    """(N, 4) rotations, wxyz, any norm."""
    opacity_logits: np.ndarray
    """(N,) opacity before the sigmoid."""
    sh: np.ndarray
    """(N, K, 3) spherical-harmonics coefficients, K = (degree + 1)², the DC term first (stgs.interop.sh)."""

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return harmonics.degree_of(self.sh.shape[1])

    def check(self, where: str) -> Splats:
        """Shapes, dtypes, count and finiteness checked (InteropError naming `where` and the field)."""
        n = self.count
        if not 0 < n <= MAX_SPLATS:
            raise InteropError(f"{where}: {n} Gaussians (between 1 and {MAX_SPLATS} are supported)")
        shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise InteropError(f"{where}: {name} has shape {getattr(self, name).shape}, not {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise InteropError(f"{where}: sh has shape {self.sh.shape}, not (N, K, 3)")
        try:
            harmonics.degree_of(self.sh.shape[1])
        except ValueError as exc:
            raise InteropError(f"{where}: {exc}") from None
        for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
            values = getattr(self, name)
            if values.dtype != np.float32:
                setattr(self, name, values := values.astype(np.float32))
            if not np.isfinite(values).all():
                bad = int((~np.isfinite(values)).reshape(n, -1).any(1).argmax())
                raise InteropError(f"{where}: {name} of Gaussian {bad} is not finite")
        if not (np.abs(self.quats).sum(1) > 0).all():
            raise InteropError(f"{where}: quats of Gaussian {int((np.abs(self.quats).sum(1) == 0).argmax())} is zero")
        return self

    def canonical(self) -> Splats:
        """The same Gaussians as every lossless format reads them back: unit rotations (`unit_quats`), log-scales
        and logits the canonical preimages of their float32 scales and opacities. Idempotent."""
        return Splats(self.means, log_scales_of(exp32(self.log_scales)), unit_quats(self.quats),
                      logits_of(sigmoid32(self.opacity_logits)), self.sh)

    def select(self, index: np.ndarray) -> Splats:
        return Splats(self.means[index], self.log_scales[index], self.quats[index], self.opacity_logits[index],
                      self.sh[index])


def preimage(forward: Callable[[np.ndarray], np.ndarray], target: np.ndarray, ideal: np.ndarray,
             steps: int = 4) -> np.ndarray:
    """Float32 x within `steps` ulps of `ideal` (float64, the exact inverse) with forward(x) == target, the
    nearest to `ideal` where several do; round(ideal) where none does."""
    ideal = np.asarray(ideal, dtype=np.float64)
    base = ideal.astype(np.float32)
    best, best_err = base.copy(), np.full(base.shape, np.inf)
    up = down = base
    candidates = [base]
    for _ in range(steps):
        up, down = np.nextafter(up, np.float32(np.inf)), np.nextafter(down, np.float32(-np.inf))
        candidates += [up, down]
    for cand in candidates:
        err = np.abs(cand.astype(np.float64) - ideal)
        better = (forward(cand) == target) & (err < best_err)
        best[better], best_err[better] = cand[better], err[better]
    return best


def sigmoid32(x: np.ndarray) -> np.ndarray:
    """Opacities (float32) of logits: the sigmoid in float64, rounded once (the glb's and a frame's forward map)."""
    with np.errstate(over="ignore"):
        return (1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))).astype(np.float32)


def exp32(x: np.ndarray) -> np.ndarray:
    """Linear scales (float32) of log scales: exp in float64, rounded once."""
    with np.errstate(over="ignore"):
        return np.exp(np.asarray(x, dtype=np.float64)).astype(np.float32)


def log_scales_of(scale: np.ndarray) -> np.ndarray:
    """Log-scales (float32) of linear scales >= 0: each the canonical preimage under exp32, within ±LOGIT_LIMIT."""
    with np.errstate(divide="ignore"):
        ideal = np.clip(np.log(np.asarray(scale, dtype=np.float64)), -LOGIT_LIMIT, LOGIT_LIMIT)
    return preimage(exp32, scale, ideal)


def logits_of(opacity: np.ndarray) -> np.ndarray:
    """Opacity logits (float32) of opacities in [0, 1]: each the canonical preimage under sigmoid32."""
    return preimage(sigmoid32, opacity, logit(opacity))


def unit_quats(quats: np.ndarray) -> np.ndarray:
    """(N, 4) rotations as unit quaternions (float32, same order): normalised in float64 and rounded once; one
    already within 1e-6 of unit norm is kept as it is, so a unit quaternion read back stays as it was."""
    q = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(np.abs(norm - 1) < 1e-6, q, q / norm).astype(np.float32)


def dc_to_colour(dc: np.ndarray) -> np.ndarray:
    """Our colour C (float32) of a DC coefficient: 0.5 + Y_0 · dc, rounded once."""
    return (0.5 + harmonics.C0 * dc.astype(np.float64)).astype(np.float32)


def colour_to_dc(colour: np.ndarray) -> np.ndarray:
    colour = np.asarray(colour, dtype=np.float32)
    return preimage(dc_to_colour, colour, (colour.astype(np.float64) - 0.5) / harmonics.C0)


def _sh1_forward(coefficients: np.ndarray) -> np.ndarray:
    return harmonics.degree1_vectors(coefficients.astype(np.float64)).astype(np.float32)


def sh1_to_coefficients(sh1: np.ndarray) -> np.ndarray:
    """Our static layer's sh1 (N, 3 axes, 3 channels) as degree-1 coefficients (N, 3, 3), canonically rounded."""
    sh1 = np.asarray(sh1, dtype=np.float32)
    ideal = harmonics.degree1_coefficients(sh1.astype(np.float64))
    out = np.empty(ideal.shape, dtype=np.float32)
    for k, (axis, sign) in enumerate(((1, -1.0), (2, 1.0), (0, -1.0))):  # coefficient k's axis in w, and sign
        def forward(c: np.ndarray, s: float = sign) -> np.ndarray:
            return (s * harmonics.C1 * c.astype(np.float64)).astype(np.float32)

        out[:, k] = preimage(forward, sh1[:, axis], ideal[:, k])
    return out


def logit(opacity: np.ndarray) -> np.ndarray:
    """Opacity logits (float64) of opacities in [0, 1], kept within ±LOGIT_LIMIT."""
    o = np.clip(np.asarray(opacity, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide="ignore"):
        return np.clip(np.log(o) - np.log1p(-o), -LOGIT_LIMIT, LOGIT_LIMIT)


def from_static(layer: StaticLayer) -> Splats:
    """A static layer's Gaussians as stored (degree 1 where it has sh1): exact, its colours canonically rounded."""
    get = lambda name: getattr(layer, name).detach().float().numpy()  # noqa: E731
    dc = colour_to_dc(get("color"))[:, None]
    sh = np.concatenate([dc, sh1_to_coefficients(get("sh1"))], 1) if layer.sh_degree else dc
    return Splats(get("xyz").copy(), get("log_scale").copy(), get("rotation").copy(), get("opacity_logit").copy(), sh)


def from_gaussians(g: Gaussians, log_scales: torch.Tensor, sh: np.ndarray | None = None) -> Splats:
    """Activated Gaussians (a deformed frame) with their scales' logs as computed (exact); opacities become
    logits, canonically rounded, and colours DC terms, or the coefficients `sh` (N, K, 3) stand for them."""
    get = lambda t: t.detach().float().numpy()  # noqa: E731
    logits = logits_of(get(g.opacities))
    sh = colour_to_dc(get(g.colors))[:, None] if sh is None else np.asarray(sh, dtype=np.float32)
    return Splats(get(g.means).copy(), get(log_scales).copy(), get(g.quats).copy(), logits, sh)


def to_static(splats: Splats) -> StaticLayer:
    """A static layer holding `splats` (degree 0 or 1; fold higher degrees first: stgs.interop.sh.fold)."""
    degree = splats.sh_degree
    if degree > 1:
        raise InteropError(f"a static layer holds spherical harmonics up to degree 1, not {degree}: fold them first")
    layer = StaticLayer(splats.count, degree)
    with torch.no_grad():
        layer.xyz.copy_(torch.from_numpy(splats.means))
        layer.log_scale.copy_(torch.from_numpy(splats.log_scales))
        layer.rotation.copy_(torch.from_numpy(splats.quats))
        layer.opacity_logit.copy_(torch.from_numpy(splats.opacity_logits))
        layer.color.copy_(torch.from_numpy(dc_to_colour(splats.sh[:, 0])))
        if degree:
            layer.sh1.copy_(torch.from_numpy(_sh1_forward(splats.sh[:, 1:4])))
    return layer
