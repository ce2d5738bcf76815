"""Vectorised residual and consistent tangent of the hyperelastic weak form.

Total Lagrangian, in the solver frame and SI units. For the mixed formulations the
volumetric energy ``kappa/2 G(J)^2`` is replaced by ``p G(J) - p^2 / (2 kappa)``
(a perturbed Lagrangian), which stays stable as ``kappa -> infinity``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .discretize import Discretization
from .kinematics import invariants, piola
from .model import Model
from .stiffness import stiffness_uu

__all__ = ["ElementState", "assemble", "external_force"]

_EYE = np.eye(3)


@dataclass(frozen=True)
class ElementState:
    """Element vectors (and matrices) of one assembly, plus the smallest J found."""

    vectors: np.ndarray  # (E, n_loc)
    matrices: np.ndarray | None  # (E, n_loc, n_loc)
    min_J: float


def deformation_gradient(disc: Discretization, x: np.ndarray) -> np.ndarray:
    """``F`` at every quadrature point, shape (E, Q, 3, 3), from the full vector ``x``."""
    u = x[: 3 * disc.n_scalar_u].reshape(-1, 3)[disc.udofs]  # (E, Au, 3)
    return np.einsum("eai,eqaj->eqij", u, disc.grad_u, optimize=True) + _EYE


def _pressure(disc: Discretization, x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    p = x[3 * disc.n_scalar_u :][disc.pdofs[idx]]  # (e, Ap)
    return np.einsum("eb,eqb->eq", p, disc.shape_p[idx])


def _energy_terms(material, F, p):
    """Energy partials with the volumetric part (or its pressure replacement) added."""
    I1, I2, J, _, _ = invariants(F)
    (W1, W2, WJ), (W11, W12, W1J, W22, W2J, WJJ) = material.partials(I1, I2, J)
    G, G1, G2 = material.volumetric.g(J)
    if p is None:
        k = material.volumetric.kappa_pa
        WJ, WJJ = WJ + k * G * G1, WJJ + k * (G1**2 + G * G2)
    else:
        WJ, WJJ = WJ + p * G1, WJJ + p * G2
    return (W1, W2, WJ), (W11, W12, W1J, W22, W2J, WJJ), J, G, G1


def _group(disc: Discretization, x, F, idx, material, tangent: bool):
    """Element vectors/matrices of the elements ``idx`` sharing one material."""
    Fg, w, dN = F[idx], disc.weights[idx], disc.grad_u[idx]
    p = _pressure(disc, x, idx) if disc.mixed else None
    first, second, J, G, G1 = _energy_terms(material, Fg, p)
    P = piola(Fg, first)
    ne = len(idx)
    r_u = np.einsum("eqij,eqaj->eai", P * w[..., None, None], dN, optimize=True).reshape(ne, -1)
    K = stiffness_uu(dN, w, Fg, first, second) if tangent else None
    if not disc.mixed:
        return r_u, K, J
    Np = disc.shape_p[idx]
    kappa = material.volumetric.kappa_pa
    r_p = np.einsum("eq,eqb->eb", w * (G - p / kappa), Np)
    if tangent:
        K = _mixed_block(K, dN, Np, w, invariants(Fg)[4] * G1[..., None, None], -w / kappa)
    return np.hstack([r_u, r_p]), K, J


def _mixed_block(K_uu, dN, Np, w, cof_G1, pp_weight) -> np.ndarray:
    """Saddle-point element matrix ``[[K_uu, K_up], [K_up^T, K_pp]]``, (E, 3A + B, 3A + B).

    ``K_up[(a,i), b] = sum_q w G'(J) (cof dN_a)_i N_b`` and ``K_pp = sum_q w/kappa N N``
    (with its sign in ``pp_weight``), written as batched matrix products.
    """
    ne, nq, na = dN.shape[:3]
    nu = 3 * na
    h = (dN @ np.swapaxes(cof_G1, -1, -2)) * w[..., None, None]  # (E, Q, A, 3)
    K_up = np.swapaxes(h.reshape(ne, nq, nu), 1, 2) @ Np  # (E, 3A, B)
    K_pp = np.swapaxes(Np * pp_weight[..., None], 1, 2) @ Np
    out = np.empty((ne, nu + Np.shape[2], nu + Np.shape[2]))
    out[:, :nu, :nu] = K_uu
    out[:, :nu, nu:] = K_up
    out[:, nu:, :nu] = np.swapaxes(K_up, 1, 2)
    out[:, nu:, nu:] = K_pp
    return out


def assemble(disc: Discretization, model: Model, x: np.ndarray, *, tangent: bool = True):
    """Internal-force element vectors and (optionally) tangent element matrices.

    Parameters
    ----------
    disc : Discretization
    model : Model
        Supplies the material of each region.
    x : ndarray, shape (n_dofs,)
        Full unknown vector (displacements in m, node-major; then pressures in Pa).
    tangent : bool
        Also compute element tangent matrices.

    Returns
    -------
    ElementState
        With ``min_J``; when any ``J <= 0`` the vectors are not meaningful.
    """
    F = deformation_gradient(disc, x)
    n_loc = _n_loc(disc)
    min_J = float(np.linalg.det(F).min())
    if min_J <= 0:
        return ElementState(np.zeros((len(F), n_loc)), None, min_J)
    groups = list(model.element_material_groups())
    if len(groups) == 1 and len(groups[0][0]) == len(F):  # one law: no scatter copies
        r, K, _ = _group(disc, x, F, groups[0][0], groups[0][1], tangent)
        return ElementState(r, K, min_J)
    vec = np.zeros((len(F), n_loc))
    mat = np.zeros((len(F), n_loc, n_loc)) if tangent else None
    for idx, material, _ in groups:
        r, K, _ = _group(disc, x, F, idx, material, tangent)
        vec[idx] = r
        if tangent:
            mat[idx] = K
    return ElementState(vec, mat, min_J)


def _n_loc(disc: Discretization) -> int:
    n = 3 * disc.udofs.shape[1]
    return n + (disc.pdofs.shape[1] if disc.mixed else 0)


def scatter(disc: Discretization, vectors: np.ndarray) -> np.ndarray:
    """Sum element vectors ``(E, n_loc)`` into a full global vector."""
    edofs = disc.element_dofs()
    return np.bincount(edofs.ravel(), weights=vectors.ravel(), minlength=disc.n_dofs)


def external_force(disc: Discretization, model: Model, gravity_m_s2: np.ndarray) -> np.ndarray:
    """Consistent nodal body force of gravity, full vector in N (solver frame).

    Parameters
    ----------
    disc : Discretization
        Of ``model.mesh``; its quadrature weights (m^3) and displacement shape functions
        integrate the load.
    model : Model
        Gives each element's density, kg/m^3.
    gravity_m_s2 : ndarray, shape (3,)
        Gravitational acceleration vector in the model frame, m/s^2.

    Returns
    -------
    ndarray, shape (disc.n_dofs,)
        Nodal forces, N, in the solver frame (``disc.R_solver_from_model``); zero on the
        pressure unknowns.
    """
    g = disc.R_solver_from_model @ np.asarray(gravity_m_s2, dtype=float)
    f = np.zeros(disc.n_dofs)
    integral = np.einsum("eq,eqa->ea", disc.weights, disc.shape_u)  # int N_a dV, m^3
    for idx, _, rho in model.element_material_groups():
        vec = (rho * integral[idx])[:, :, None] * g  # (e, Au, 3)
        np.add.at(f, (3 * disc.udofs[idx][:, :, None] + np.arange(3)).ravel(), vec.ravel())
    return f
