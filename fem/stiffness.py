"""Element stiffness of the displacement block, with a fast path for laws free of I2.

The displacement-displacement element matrix is

    K[(a,i),(b,k)] = sum_q w_q sum_JL dN_aJ A_iJkL dN_bL

with ``A = dP/dF``. Built from the full ``(E, Q, 3, 3, 3, 3)`` tangent this is a
large contraction. For energies ``W(I1, J)`` (neo-Hookean in either convention, and
every law whose ``W2``, ``W12``, ``W22``, ``W2J`` vanish) the tangent is a short sum of
products of 3x3 tensors,

    A = sum_mn H_mn Dm (x) Dn + 2 W1 I + (WJ / J) (cof (x) cof - cof (x)_swap cof),

with ``D1 = 2F``, ``DJ = cof F`` and ``H = [[W11, W1J], [W1J, WJJ]]``, so ``K`` follows
from per-point vectors ``g^m_ai = sum_J Dm_iJ dN_aJ`` with batched matrix products of
inner size ``2 Q`` and ``Q``. Both paths give the same matrix to round-off (tested).
"""

from __future__ import annotations

import numpy as np

from .kinematics import invariants, piola_and_tangent

__all__ = ["stiffness_uu"]


def stiffness_uu(dN, w, F, first, second) -> np.ndarray:
    """Displacement block of the element tangents.

    Parameters
    ----------
    dN : ndarray, shape (E, Q, A, 3)
        Reference gradients of the displacement shape functions, 1/m.
    w : ndarray, shape (E, Q)
        Quadrature weights times the element volume factor, m^3.
    F : ndarray, shape (E, Q, 3, 3)
        Deformation gradients.
    first, second : tuple of ndarray, each of shape (E, Q)
        ``(W1, W2, WJ)`` and ``(W11, W12, W1J, W22, W2J, WJJ)`` of the energy, with the
        volumetric part (or its pressure replacement) included.

    Returns
    -------
    ndarray, shape (E, 3 A, 3 A)
        Node-major local ordering ``(a, i)``, N/m.
    """
    W2, (W12, W22, W2J) = first[1], (second[1], second[3], second[4])
    if any(np.any(t != 0.0) for t in (W2, W12, W22, W2J)):
        return stiffness_uu_general(dN, w, F, first, second)
    return stiffness_uu_i1j(dN, w, F, first, second)


def stiffness_uu_general(dN, w, F, first, second) -> np.ndarray:
    """Any invariant law: contraction of the full fourth-order tangent."""
    _, A = piola_and_tangent(F, first, second)
    ne, na = dN.shape[0], dN.shape[2]
    T = np.einsum("eqaj,eqijkl->eqaikl", dN, A * w[..., None, None, None, None], optimize=True)
    K = np.einsum("eqaikl,eqbl->eaibk", T, dN, optimize=True)
    return K.reshape(ne, 3 * na, 3 * na)


def stiffness_uu_i1j(dN, w, F, first, second) -> np.ndarray:
    """Laws ``W(I1, J)``: the tangent's rank-one and identity structure (module docstring)."""
    ne, nq, na = dN.shape[:3]
    W1, _, WJ = first
    W11, _, W1J, _, _, WJJ = second
    _, _, J, _, cof = invariants(F)
    g1 = 2.0 * dN @ np.swapaxes(F, -1, -2)  # (E, Q, A, 3)
    gJ = dN @ np.swapaxes(cof, -1, -2)
    c = WJ / J
    H = np.stack([np.stack([W11, W1J], -1), np.stack([W1J, WJJ + c], -1)], -2)  # (E,Q,2,2)
    G = np.stack([g1, gJ], axis=2).reshape(ne, nq, 2, 3 * na)  # (E, Q, 2, 3A)
    GH = (H * w[..., None, None]) @ G  # (E, Q, 2, 3A)
    K = _qsum_outer(G.reshape(ne, nq * 2, -1), GH.reshape(ne, nq * 2, -1))
    S = _qsum_outer(gJ.reshape(ne, nq, -1), (c * w)[..., None] * gJ.reshape(ne, nq, -1))
    K = K.reshape(ne, na, 3, na, 3)
    K -= S.reshape(ne, na, 3, na, 3).transpose(0, 1, 4, 3, 2)
    L = _qsum_outer(_stack_q(dN), _stack_q(dN * (2.0 * W1 * w)[..., None, None]))
    for i in range(3):
        K[:, :, i, :, i] += L
    return K.reshape(ne, 3 * na, 3 * na)


def _stack_q(dN: np.ndarray) -> np.ndarray:
    """(E, Q, A, 3) -> (E, Q*3, A): quadrature point and direction as one summed axis."""
    ne, nq, na, _ = dN.shape
    return dN.transpose(0, 1, 3, 2).reshape(ne, nq * 3, na)


def _qsum_outer(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``sum_s left[e, s, m] right[e, s, n]`` for (E, S, M) and (E, S, N) arrays."""
    return np.swapaxes(left, 1, 2) @ right
