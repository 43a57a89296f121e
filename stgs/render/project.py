"""EWA projection of 3D Gaussians to screen space (pure torch, differentiable).

The reference splatter's projection, and the torch twin of the native one (csrc/project.cpp) and of its
gradient (stgs_project_backward), which the parity tests hold to autograd through this code. The constants
here are the splatter contract of docs/ARCHITECTURE.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

NEAR_Z = 0.01
"""Gaussians whose camera-space depth is below this are culled."""
COV_BLUR = 0.3
"""Added to the diagonal of every 2D covariance, in px²."""
ALPHA_MIN = 1.0 / 255.0
"""Contributions below this alpha are skipped."""
ALPHA_MAX = 0.99
"""Alpha is clamped to this."""
T_MIN = 1e-4
"""Compositing stops before a contribution that would take transmittance below this."""
EXTENT_MARGIN = 1.0 + 1e-4
"""Relative safety margin on screen extents so float rounding never drops a pixel."""


@dataclass
class Projected:
    """Screen-space Gaussians, in the dtype the projection ran in."""

    means2d: torch.Tensor
    """(N, 2) projected centres in pixel coordinates (pixel (u, v) is centred at u+0.5, v+0.5)."""
    conics: torch.Tensor
    """(N, 3) inverse 2D covariance (a, b, c): q = a dx² + 2 b dx dy + c dy²."""
    depths: torch.Tensor
    """(N,) camera-space depth of the mean (sort key)."""
    extents: torch.Tensor
    """(N, 2) half-widths of the screen box where alpha can reach 1/255; -1 for culled Gaussians."""


def normalize_quats(quats: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (wxyz), overflow-safe; a zero quaternion becomes the identity rotation.

    Gradients stay finite for zero and huge inputs (double-where trick).
    """
    peak = quats.abs().amax(dim=-1, keepdim=True)
    nonzero = peak > 0
    scaled = quats / torch.where(nonzero, peak, torch.ones_like(peak))
    norm = torch.linalg.vector_norm(scaled, dim=-1, keepdim=True)
    unit = scaled / torch.where(nonzero, norm, torch.ones_like(norm))
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    return torch.where(nonzero, unit, identity)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz quaternions (any norm) -> (N, 3, 3) rotation matrices."""
    w, x, y, z = normalize_quats(quats).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def screen_extents(cov_xx: torch.Tensor, cov_yy: torch.Tensor, opacities: torch.Tensor,
                   valid: torch.Tensor) -> torch.Tensor:
    """Opacity-aware half-widths of the screen box outside which alpha < 1/255."""
    level = 255.0 * opacities
    reach = valid & (level >= 1.0)
    quad = 2.0 * torch.log(torch.where(reach, level, torch.ones_like(level)))
    hx = torch.sqrt(quad * cov_xx) * EXTENT_MARGIN + 1e-3
    hy = torch.sqrt(quad * cov_yy) * EXTENT_MARGIN + 1e-3
    ext = torch.stack([hx, hy], dim=-1)
    return torch.where(reach[:, None], ext, torch.full_like(ext, -1.0))


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
            opacities: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> Projected:
    """Project Gaussians with the EWA approximation Σ' = J W Σ Wᵀ Jᵀ + 0.3 I.

    The determinant is formed from squared 2x2 minors (Cauchy-Binet) so it stays
    positive and accurate for extremely anisotropic Gaussians.
    """
    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    K = K.to(dtype)
    rot_cw = viewmat[:3, :3]
    p_cam = means @ rot_cw.T + viewmat[:3, 3]
    x, y, z = p_cam.unbind(-1)
    valid = z >= NEAR_Z
    z = torch.where(valid, z, torch.ones_like(z))
    xn, yn = x / z, y / z
    u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
    v = K[1, 1] * yn + K[1, 2]
    zero = torch.zeros_like(z)
    # d(xn, yn)/d(p_cam), then through the intrinsics' 2x2 block.
    d_norm = torch.stack([1 / z, zero, -xn / z, zero, 1 / z, -yn / z], -1).reshape(-1, 2, 3)
    jac = K[:2, :2] @ d_norm
    M = jac @ rot_cw @ quat_to_rotmat(quats) * scales[:, None, :]
    m1, m2 = M[:, 0], M[:, 1]
    a0 = (m1 * m1).sum(-1)
    b0 = (m1 * m2).sum(-1)
    c0 = (m2 * m2).sum(-1)
    minors = torch.stack([m1[:, 0] * m2[:, 1] - m1[:, 1] * m2[:, 0],
                          m1[:, 0] * m2[:, 2] - m1[:, 2] * m2[:, 0],
                          m1[:, 1] * m2[:, 2] - m1[:, 2] * m2[:, 1]], -1)
    det = (minors * minors).sum(-1) + COV_BLUR * (a0 + c0) + COV_BLUR * COV_BLUR
    conics = torch.stack([(c0 + COV_BLUR) / det, -b0 / det, (a0 + COV_BLUR) / det], -1)
    with torch.no_grad():
        extents = screen_extents(a0 + COV_BLUR, c0 + COV_BLUR, opacities.to(dtype), valid)
    return Projected(torch.stack([u, v], -1), conics, torch.where(valid, z, torch.full_like(z, -1.0)),
                     extents)
