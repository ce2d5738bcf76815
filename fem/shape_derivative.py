"""Derivative of the residual with respect to the reference (stress-free) node positions.

Needed for sensitivities of the stress-free reference recovery. With the geometry
perturbation gradient ``G = sum_c dX_c (x) grad M_c`` (``M_c`` the vertex hat functions
of the affine element map): ``d grad N = -G^T grad N``, ``d dV = tr(G) dV`` and
``dF = -H G`` with ``H = grad u``. The element matrices have the displacement
element's layout; only the vertex columns (the geometry) are non-zero.
"""

from __future__ import annotations

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


def _group_geometry(disc, x, F, idx, material, rho, g):
    """Element geometry matrices ``d r / d X`` of elements sharing a material, (e, n, 4, 3)."""
    Fg, w, dN, Nu = F[idx], disc.weights[idx], disc.grad_u[idx], disc.shape_u[idx]
    dM = _vertex_gradients(disc)[idx]
    p = _pressure(disc, x, idx) if disc.mixed else None
    first, second, J, Gv, G1 = _energy_terms(material, Fg, p)
    P, A = piola_and_tangent(Fg, first, second)
    H = Fg - np.eye(3)
    # term 1: -dN_aJ A_iJkL H_km dM_cL ; term 2: -(P dM_c)_i dN_am ; term 3: (P dN_a)_i dM_cm
    AH = np.einsum("eqijkl,eqkm->eqijml", A, H, optimize=True)
    t1 = -np.einsum("eq,eqaj,eqijml,ecl->eaicm", w, dN, AH, dM, optimize=True)
    t2 = -np.einsum("eq,eqij,ecj,eqam->eaicm", w, P, dM, dN, optimize=True)
    t3 = np.einsum("eq,eqij,eqaj,ecm->eaicm", w, P, dN, dM, optimize=True)
    ext = -np.einsum("eq,eqa,i,ecm->eaicm", w * rho, Nu, g, dM, optimize=True)
    D = (t1 + t2 + t3 + ext).reshape(len(idx), -1, 4, 3)
    if not disc.mixed:
        return D
    cof = invariants(Fg)[4]
    Np = disc.shape_p[idx]
    kappa = material.volumetric.kappa_pa
    dJ = -np.einsum("eqkl,eqkm,ecl->eqcm", cof, H, dM, optimize=True)
    Dp = np.einsum("eq,eqcm,eqb->ebcm", w * G1, dJ, Np, optimize=True)
    Dp += np.einsum("eq,eqb,ecm->ebcm", w * (Gv - p / kappa), Np, dM, optimize=True)
    return np.concatenate([D, Dp], axis=1)


def geometry_matrices(
    disc: Discretization, model: Model, x: np.ndarray, gravity_m_s2: np.ndarray
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

    Returns
    -------
    ndarray, shape (E, n_loc, n_loc)
        Column ``3 c + m`` of an element holds the derivative with respect to the
        ``m``-th coordinate (solver frame, m) of its vertex ``c``; other columns are 0.
        Use with ``disc.pattern.matrix`` to get the free-dof matrix.
    """
    g = disc.R_solver_from_model @ np.asarray(gravity_m_s2, float)
    F = deformation_gradient(disc, x)
    n_loc = disc.element_dofs().shape[1]
    out = np.zeros((len(F), n_loc, n_loc))
    for idx, material, rho in model.element_material_groups():
        D = _group_geometry(disc, x, F, idx, material, rho, g)
        out[idx, :, :12] = D.reshape(len(idx), n_loc, 12)
    return out
