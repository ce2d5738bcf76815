"""Stress and consistent tangent of an invariant-based energy, for arrays of F.

All functions take deformation gradients of shape ``(..., 3, 3)`` and broadcast
over the leading axes (elements, quadrature points). For ``W(I1, I2, J)``::

    P = W1 D1 + W2 D2 + WJ DJ
    A = sum_ab Wab Da (x) Db + sum_a Wa dDa/dF

with ``D1 = 2F``, ``D2 = 2 (I1 F - F C)`` and ``DJ = cof F``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["invariants", "piola_and_tangent", "piola"]

_EYE = np.eye(3)


def invariants(F: np.ndarray) -> tuple[np.ndarray, ...]:
    """Return ``I1, I2, J, C, cof`` of deformation gradients ``F (..., 3, 3)``."""
    C = np.einsum("...ki,...kj->...ij", F, F)
    I1 = np.einsum("...ii->...", C)
    I2 = 0.5 * (I1**2 - np.einsum("...ij,...ji->...", C, C))
    cof = cofactor(F)
    J = np.einsum("...j,...j->...", F[..., 0, :], cof[..., 0, :])  # Laplace expansion
    return I1, I2, J, C, cof


def cofactor(F: np.ndarray) -> np.ndarray:
    """Cofactor matrix ``J F^-T`` of ``F (..., 3, 3)``, computed without inversion."""
    a = F[..., [1, 2, 0], :]
    b = F[..., [2, 0, 1], :]
    cof = np.cross(a, b)
    return cof


def _directions(F, I1, C, cof):
    D1 = 2.0 * F
    D2 = 2.0 * (I1[..., None, None] * F - F @ C)
    return D1, D2, cof


def piola(F: np.ndarray, first: tuple[np.ndarray, ...]) -> np.ndarray:
    """First Piola-Kirchhoff stress from the energy's first partials ``(W1, W2, WJ)``."""
    I1, _, _, C, cof = invariants(F)
    D1, D2, DJ = _directions(F, I1, C, cof)
    W1, W2, WJ = (w[..., None, None] for w in first)
    return W1 * D1 + W2 * D2 + WJ * DJ


def _d_cof(J: np.ndarray, cof: np.ndarray) -> np.ndarray:
    """``d(cof F)_iJ / dF_kL = (cof_iJ cof_kL - cof_iL cof_kJ) / J``."""
    outer = np.einsum("...ij,...kl->...ijkl", cof, cof)
    swap = np.einsum("...il,...kj->...ijkl", cof, cof)
    return (outer - swap) / J[..., None, None, None, None]


def _d_d2(F: np.ndarray, I1: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``dD2/dF`` with ``D2 = 2 (I1 F - F C)``."""
    b = np.einsum("...ik,...jk->...ij", F, F)
    eye4 = np.einsum("ik,jl->ijkl", _EYE, _EYE)
    t = 2.0 * np.einsum("...ij,...kl->...ijkl", F, F)
    t += I1[..., None, None, None, None] * eye4
    t -= np.einsum("ik,...lj->...ijkl", _EYE, C)
    t -= np.einsum("...il,...kj->...ijkl", F, F)
    t -= np.einsum("...ik,jl->...ijkl", b, _EYE)
    return 2.0 * t


def piola_and_tangent(
    F: np.ndarray, first: tuple[np.ndarray, ...], second: tuple[np.ndarray, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Stress ``P (..., 3, 3)`` and tangent ``A = dP/dF (..., 3, 3, 3, 3)``.

    Parameters
    ----------
    F : ndarray, shape (..., 3, 3)
        Deformation gradients.
    first : tuple of ndarray
        ``(W1, W2, WJ)``, each of shape ``(...)``.
    second : tuple of ndarray
        ``(W11, W12, W1J, W22, W2J, WJJ)``, each of shape ``(...)``.
    """
    I1, _, J, C, cof = invariants(F)
    D = _directions(F, I1, C, cof)
    W1, W2, WJ = first
    W11, W12, W1J, W22, W2J, WJJ = second
    P = sum(w[..., None, None] * d for w, d in zip(first, D, strict=True))
    hess = ((W11, W12, W1J), (W12, W22, W2J), (W1J, W2J, WJJ))
    A = _sym_outer_sum(hess, D)
    A += 2.0 * W1[..., None, None, None, None] * np.einsum("ik,jl->ijkl", _EYE, _EYE)
    if np.any(W2 != 0.0):
        A += W2[..., None, None, None, None] * _d_d2(F, I1, C)
    A += WJ[..., None, None, None, None] * _d_cof(J, cof)
    return P, A


def _sym_outer_sum(hess, D) -> np.ndarray:
    A = np.zeros(D[0].shape + (3, 3))
    for a in range(3):
        for b in range(3):
            w = hess[a][b]
            if np.any(w != 0.0):
                A += w[..., None, None, None, None] * np.einsum("...ij,...kl->...ijkl", D[a], D[b])
    return A
