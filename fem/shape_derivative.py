"""Derivative of the residual with respect to the reference (stress-free) node positions.

Needed for the inverse problem of the stress-free reference and its sensitivities. With
the geometry perturbation gradient ``G = sum_c dX_c (x) grad M_c`` (``M_c`` the shape
functions of the element map): ``d grad N = -G^T grad N``, ``d dV = tr(G) dV`` and
``dF = -H G`` with ``H = grad u`` (Eqs. (1)-(3) below; e.g. Govindjee & Mihalic 1998,
Sect. 3). Two element maps:

- ``"affine"``: straight-sided elements, ``M_c`` the 4 vertex hat functions, ``G``
  constant per element; only the vertex columns of the matrices are non-zero.
- ``"isoparametric"``: the geometry is interpolated with the displacement's own shape
  functions (P2 for Taylor-Hood), ``G`` varies over the element; every displacement
  column is a geometry column. ``disc`` must then carry the curved geometry's
  gradients and weights at each quadrature point (see :mod:`fem.prestress`).

References
----------
Govindjee, S. & Mihalic, P. A. (1998). Computational methods for inverse deformations in
quasi-incompressible finite elasticity. *IJNME* 43, 821-838.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .assemble import _energy_terms, _pressure, deformation_gradient
from .discretize import Discretization, _jacobians
from .kinematics import invariants, piola_and_tangent
from .model import Model

__all__ = ["geometry_matrices"]

_DM_REF = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _vertex_gradients(disc: Discretization) -> np.ndarray:
    """Gradients of the 4 vertex hat functions per element, (E, 4, 3), 1/m."""
    jinv = np.linalg.inv(_jacobians(disc.mesh, disc.R_solver_from_model))
    return np.einsum("cm,emj->ecj", _DM_REF, jinv)


def _term1(w, dN, A, H, dM) -> np.ndarray:
    """``sum_q w dN_aJ A_iJkL H_km dM_cL`` as batched matrix products, (e, a, i, c, m)."""
    e, q, na = dN.shape[:3]
    nc = dM.shape[2]
    Aw = (A * w[..., None, None, None, None]).reshape(e, q, 3, 3, 9).swapaxes(2, 3)
    B = (dN @ Aw.reshape(e, q, 3, 27)).reshape(e, q, na * 9, 3)  # (a, i, k) x L
    T = (B @ dM.swapaxes(2, 3)).reshape(e, q, na, 3, 3, nc)  # a, i, k, c
    out = T.swapaxes(4, 5) @ H[:, :, None, None]  # a, i, c, m
    return out.sum(axis=1)


def _group_geometry(disc, x, F, idx, material, rho, g, dM):
    """Element geometry matrices ``d r / d X`` of elements sharing a material, (e, n, C, 3).

    ``dM`` (e, Q, C, 3) holds the gradients of the ``C`` geometry shape functions at
    each quadrature point.
    """
    Fg, w, dN, Nu = F[idx], disc.weights[idx], disc.grad_u[idx], disc.shape_u[idx]
    p = _pressure(disc, x, idx) if disc.mixed else None
    first, second, J, Gv, G1 = _energy_terms(material, Fg, p)
    P, A = piola_and_tangent(Fg, first, second)
    H = Fg - np.eye(3)
    nc = dM.shape[2]
    # Eq. (1) dF = -H G, (2) d grad N = -G^T grad N, (3) d dV = tr(G) dV, in
    # term 1: -dN_aJ A_iJkL H_km dM_cL ; term 2: -(P dM_c)_i dN_am ; term 3: (P dN_a)_i dM_cm
    t1 = -_term1(w, dN, A, H, dM)
    t2 = -np.einsum("eq,eqij,eqcj,eqam->eaicm", w, P, dM, dN, optimize=True)
    t3 = np.einsum("eq,eqij,eqaj,eqcm->eaicm", w, P, dN, dM, optimize=True)
    ext = -np.einsum("eq,eqa,i,eqcm->eaicm", w * rho, Nu, g, dM, optimize=True)
    D = (t1 + t2 + t3 + ext).reshape(len(idx), -1, nc, 3)
    if not disc.mixed:
        return D
    cof = invariants(Fg)[4]
    Np = disc.shape_p[idx]
    kappa = material.volumetric.kappa_pa
    dJ = -np.einsum("eqkl,eqkm,eqcl->eqcm", cof, H, dM, optimize=True)
    Dp = np.einsum("eq,eqcm,eqb->ebcm", w * G1, dJ, Np, optimize=True)
    Dp += np.einsum("eq,eqb,eqcm->ebcm", w * (Gv - p / kappa), Np, dM, optimize=True)
    return np.concatenate([D, Dp], axis=1)


def geometry_matrices(
    disc: Discretization,
    model: Model,
    x: np.ndarray,
    gravity_m_s2: np.ndarray,
    *,
    geometry: Literal["affine", "isoparametric"] = "affine",
) -> np.ndarray:
    """Element matrices of ``d(R_int - f_ext)/dX`` in the element-dof layout.

    Parameters
    ----------
    disc : Discretization
    model : Model
    x : ndarray, shape (n_dofs,)
        State at which to differentiate (solver frame, SI).
    gravity_m_s2 : ndarray, shape (3,)
        Gravity vector in the model frame.
    geometry : {"affine", "isoparametric"}
        The element map (module docstring).

    Returns
    -------
    ndarray, shape (E, n_loc, n_loc)
        Column ``3 c + m`` of an element holds the derivative with respect to the
        ``m``-th coordinate (solver frame, m) of its geometry node ``c`` (its vertex for
        ``affine``, its displacement node for ``isoparametric``); other columns are 0.
        Use with ``disc.pattern.matrix`` to get the free-dof matrix.
    """
    if geometry not in ("affine", "isoparametric"):
        raise ValueError(f"geometry must be 'affine' or 'isoparametric', got {geometry!r}")
    g = disc.R_solver_from_model @ np.asarray(gravity_m_s2, float)
    F = deformation_gradient(disc, x)
    n_loc = disc.element_dofs().shape[1]
    if geometry == "affine":
        dM_all = _vertex_gradients(disc)[:, None]  # constant over the element
    out = np.zeros((len(F), n_loc, n_loc))
    for idx, material, rho in model.element_material_groups():
        if geometry == "affine":
            dM = np.broadcast_to(dM_all[idx], (len(idx), F.shape[1], 4, 3))
        else:
            dM = disc.grad_u[idx]
        D = _group_geometry(disc, x, F, idx, material, rho, g, dM)
        nc = 3 * dM.shape[2]
        out[idx, :, :nc] = D.reshape(len(idx), n_loc, nc)
    return out
