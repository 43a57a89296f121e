"""Real spherical harmonics as the 3DGS ecosystem evaluates them (degrees 0 to 3), and what maps onto ours.

A 3DGS colour seen along the unit direction d (from the camera to the mean) is

    colour = max(0, 0.5 + Σ_k Y_k(d) · sh[k])         k < (degree + 1)², sh[0] the DC term

with the basis, constants and signs of the reference 3DGS code (`eval_sh`). Our static layer's colour is
relu(C) + Σ_i d_i · sh1[i] (stgs.model.static): the DC term and degree 1 map onto it exactly (C = 0.5 + Y_0 · sh[0];
degree 1 is linear in d), the clamp moves from the sum to C alone. Degrees 2 and 3 have no counterpart and are
folded into degrees 0 and 1 (`fold`).
"""

from __future__ import annotations

import numpy as np

C0 = 0.28209479177387814
"""Y_0 (the DC term's constant)."""
C1 = 0.4886025119029199
"""|Y_1| per axis."""
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)

MAX_DEGREE = 3
"""Highest degree a file may carry."""

# Signs of each coefficient under (x, y, z) -> (x, -y, -z), a half turn about x: OpenCV's right/down/forward axes
# against SPZ's right/up/back. Degree 1 is (y, z, x); a basis function changes sign with the parity of its y and z.
HALF_TURN_X_SIGNS = np.array([1.0, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)


def coefficients(degree: int) -> int:
    """(degree + 1)²: coefficients per channel up to `degree`."""
    return (degree + 1) ** 2


def degree_of(count: int) -> int:
    """The degree with `count` coefficients per channel (ValueError when none has)."""
    for degree in range(MAX_DEGREE + 1):
        if coefficients(degree) == count:
            return degree
    raise ValueError(f"{count} coefficients per channel is no spherical-harmonics degree up to {MAX_DEGREE}")


def basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """(..., (degree+1)²) the basis Y_k at unit directions (..., 3), float64."""
    x, y, z = (dirs[..., i].astype(np.float64) for i in range(3))
    out = [np.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, -1)


def evaluate(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N, 3) unclamped 0.5 + Σ_k Y_k(d) sh[k] for sh (N, K, 3) and unit directions (N, 3) (float64)."""
    y = basis(dirs, degree_of(sh.shape[1]))
    return 0.5 + np.einsum("nk,nkc->nc", y, sh.astype(np.float64))


def fold(sh: np.ndarray, dirs: np.ndarray | None = None, ridge: float = 1e-3) -> np.ndarray:
    """(N, 4, 3) degree-1 coefficients standing for sh (N, K, 3) of a higher degree.

    Without `dirs` the higher degrees are dropped, which is the closest degree-1 colour over the whole sphere (the
    basis is orthonormal). With `dirs` (N, M, 3), unit directions from M cameras to each mean, the degree-1 colour
    is fitted by least squares to the full one at those directions, as the cameras will see it, with a `ridge`
    pull towards the dropped form so that directions from one side still give a well-posed fit."""
    sh = sh.astype(np.float64)
    kept = sh[:, :4]
    if sh.shape[1] <= 4 or dirs is None:
        return kept.copy()
    return fit_degree1(np.einsum("nmk,nkc->nmc", basis(dirs, degree_of(sh.shape[1])), sh), dirs, kept, ridge)


def fit_degree1(values: np.ndarray, dirs: np.ndarray, prior: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """(N, 4, 3) coefficients c minimising Σ_m |Σ_k Y_k(d_nm) c_nk - values_nm|² + ridge·M·|c_n - prior_n|² for
    values (N, M, 3) seen along unit directions dirs (N, M, 3) (colours less 0.5, in the SH form)."""
    low = basis(dirs, 1)                                                        # (N, M, 4)
    m = dirs.shape[1]
    gram = np.einsum("nmk,nml->nkl", low, low) + ridge * m * np.eye(4)
    rhs = np.einsum("nmk,nmc->nkc", low, values.astype(np.float64)) + ridge * m * prior.astype(np.float64)
    return np.linalg.solve(gram, rhs)


def degree1_vectors(sh1: np.ndarray) -> np.ndarray:
    """Degree-1 coefficients (N, 3, 3), in the basis order (y, z, x), as the vectors w (N, 3 axes x y z, 3 channels)
    with Σ_k Y_k(d) sh[k] = d · w per channel: our static layer's sh1 (float64)."""
    return np.stack([-C1 * sh1[:, 2], -C1 * sh1[:, 0], C1 * sh1[:, 1]], 1)


def degree1_coefficients(vectors: np.ndarray) -> np.ndarray:
    """degree1_vectors' inverse: vectors w (N, 3 axes, 3 channels) -> coefficients (N, 3, 3) in (y, z, x) order."""
    return np.stack([-vectors[:, 1] / C1, vectors[:, 2] / C1, -vectors[:, 0] / C1], 1)
