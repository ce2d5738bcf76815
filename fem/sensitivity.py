"""Direct sensitivities of converged gravity solutions to a model parameter.

For a converged state ``u`` of ``R(u; X, p) = 0`` (internal minus external force on
stress-free nodes ``X``, a material or load parameter ``p``), differentiating gives the
direct sensitivity ``K du/dp = -dR/dp - D dX/dp`` with ``K`` the consistent tangent and
``D = dR/dX`` the residual's shape derivative (:mod:`fem.shape_derivative`): one
factorisation per state. When ``X`` is itself the stress-free geometry recovered from a
loaded scan ``x_m`` (``X = x_m - u0``, :mod:`fem.unload`), differentiating
``R(u0; x_m - u0, p) = 0`` gives ``(K0 - D0) du0/dp = -dR/dp`` at the reference load.

``dR/dp`` is taken by central differences of the model in ``p`` at the fixed state: the
residual is an explicit, smooth function of the material parameters, so the difference
error is ``O(eps^2)`` relative (1e-12 at ``eps = 1e-6``), far below the Newton tolerance.

A support's springs (an elastic or sliding back) enter ``R`` and ``K`` as in the solver;
their force is per unit area of the stress-free face, so they enter ``D`` too
(:func:`fem.discretize.spring_shape_derivative`).

References
----------
Kleiber, M., Antunez, H., Hien, T. D. & Kowalczyk, P. (1997). *Parameter Sensitivity in
Nonlinear Mechanics*. Wiley (the direct differentiation method, ch. 3).
Govindjee, S. & Mihalic, P. A. (1996). Computational methods for inverse finite
elastostatics. *CMAME* 136, 47-57 (the inverse problem being differentiated).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .assemble import assemble, external_force, scatter
from .discretize import Discretization, spring_shape_derivative
from .linalg import factorize
from .model import Model
from .shape_derivative import geometry_matrices

__all__ = [
    "geometry_matrix",
    "parameter_derivative",
    "residual",
    "state_sensitivity",
    "stress_free_sensitivity",
    "tangent_matrix",
    "vertex_dofs",
]

ModelAt = Callable[[float], Model]


def residual(
    disc: Discretization, model: Model, state: np.ndarray, gravity_m_s2: np.ndarray
) -> np.ndarray:
    """Full residual vector ``R_int - f_ext`` (N; pressure rows in m^3) at a state.

    Parameters
    ----------
    disc : Discretization
        On the stress-free nodes.
    model : Model
        Materials and densities (its mesh topology must be ``disc``'s).
    state : ndarray, shape (n_dofs,)
    gravity_m_s2 : ndarray, shape (3,)
        Gravity acceleration vector, model frame (:func:`fem.fields.gravity_vector`).
    """
    st = assemble(disc, model, state, tangent=False)
    r = scatter(disc, st.vectors) - external_force(disc, model, gravity_m_s2)
    if disc.spring is not None:  # a support's springs, as in the solver
        r += disc.spring @ state
    return r


def parameter_derivative(
    disc: Discretization,
    model_at: ModelAt,
    p: float,
    state: np.ndarray,
    gravity_m_s2: np.ndarray,
    *,
    eps: float = 1e-6,
) -> np.ndarray:
    """``dR/dp`` at a fixed state by central differences of the model, (n_dofs,)."""
    rp = residual(disc, model_at(p + eps), state, gravity_m_s2)
    rm = residual(disc, model_at(p - eps), state, gravity_m_s2)
    return (rp - rm) / (2.0 * eps)


def tangent_matrix(
    disc: Discretization,
    model: Model,
    state: np.ndarray,
    *,
    shape_load_m_s2: np.ndarray | None = None,
):
    """Free-dof consistent tangent ``K``; with ``shape_load_m_s2`` the inverse tangent ``K - D``.

    Parameters
    ----------
    disc : Discretization
        On the stress-free nodes.
    model : Model
        Materials and densities (its mesh topology must be ``disc``'s).
    state : ndarray, shape (n_dofs,)
        Full solver vector (solver frame, SI: displacements in m, pressures in Pa), e.g.
        ``Solution.state``.
    shape_load_m_s2 : ndarray, shape (3,), optional
        Gravity of the shape derivative ``D`` to subtract (the inverse problem's
        Jacobian, :mod:`fem.unload`), model frame, m/s^2.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n_free, n_free)
        Over ``disc.free``, SI (N/m on the displacement rows and columns), a support's
        springs included.
    """
    Ke = assemble(disc, model, state, tangent=True).matrices
    if shape_load_m_s2 is not None:
        Ke = Ke - geometry_matrices(disc, model, state, shape_load_m_s2)
    K = disc.pattern.matrix(Ke)
    free = disc.free
    if disc.spring is not None:  # a support's springs, as in the solver
        K = K + disc.spring[free][:, free]
        if shape_load_m_s2 is not None:
            K = K - spring_shape_derivative(disc, state)[free][:, free]
    return K


def geometry_matrix(
    disc: Discretization, model: Model, state: np.ndarray, gravity_m_s2: np.ndarray
):
    """Free-dof shape derivative ``D = dR/dX`` (vertex columns only), sparse."""
    D = disc.pattern.matrix(geometry_matrices(disc, model, state, gravity_m_s2))
    if disc.spring is not None:  # springs per unit area of the moving face
        D = D + spring_shape_derivative(disc, state)[disc.free][:, disc.free]
    return D


def vertex_dofs(disc: Discretization) -> np.ndarray:
    """Indices of the vertices' displacement unknowns in the full vector, (3 n_nodes,)."""
    return (3 * disc.skfem_basis.nodal_dofs[0][:, None] + np.arange(3)).ravel()


def stress_free_sensitivity(
    disc0: Discretization,
    model_at: ModelAt,
    p: float,
    u0: np.ndarray,
    gravity_m_s2: np.ndarray,
) -> np.ndarray:
    """``du0/dp`` of the recovered reference displacement (full vector, solver units).

    Differentiates ``R(u0; x_m - u0, p) = 0``: ``(K0 - D0) du0 = -dR/dp``.

    Parameters
    ----------
    disc0 : Discretization
        On the recovered stress-free nodes ``X = x_m - u0``.
    model_at : callable
        ``model_at(p) -> Model`` with the parameter value ``p``.
    p : float
    u0 : ndarray, shape (n_dofs,)
        The converged reference state (``ReferenceRecovery.solution.state``).
    gravity_m_s2 : ndarray, shape (3,)
        Gravity of the reference scan.
    """
    model = model_at(p)
    M = tangent_matrix(disc0, model, u0, shape_load_m_s2=gravity_m_s2)
    rhs = -parameter_derivative(disc0, model_at, p, u0, gravity_m_s2)
    du0 = np.zeros(disc0.n_dofs)
    du0[disc0.free] = factorize(M)(rhs[disc0.free])
    return du0


def state_sensitivity(
    disc: Discretization,
    model_at: ModelAt,
    p: float,
    state: np.ndarray,
    gravity_m_s2: np.ndarray,
    *,
    dX_state: np.ndarray | None = None,
) -> np.ndarray:
    """``du/dp`` of a converged forward state (full vector, solver units).

    Solves ``K du = -dR/dp - D dX`` (one factorisation).

    Parameters
    ----------
    disc : Discretization
        On the stress-free nodes.
    model_at : callable
        ``model_at(p) -> Model`` with the parameter value ``p``.
    p : float
        The parameter's value at the state (in the unit ``model_at`` takes).
    state : ndarray, shape (n_dofs,)
        The converged state (``Solution.state``: solver frame, SI).
    gravity_m_s2 : ndarray, shape (3,)
        Gravity acceleration vector the state was solved under, model frame, m/s^2.
    dX_state : ndarray, shape (n_dofs,), optional
        Derivative of the stress-free geometry in ``p`` as a solver vector on the vertex
        dofs (metres, solver frame; e.g. ``-du0`` there), when the geometry moves with ``p``.

    Returns
    -------
    ndarray, shape (n_dofs,)
        ``du/dp``, solver frame, SI per unit of ``p`` (zero on the fixed dofs).
    """
    model = model_at(p)
    free = disc.free
    rhs = -parameter_derivative(disc, model_at, p, state, gravity_m_s2)[free]
    if dX_state is not None:
        rhs -= geometry_matrix(disc, model, state, gravity_m_s2) @ dX_state[free]
    du = np.zeros(disc.n_dofs)
    du[free] = factorize(tangent_matrix(disc, model, state))(rhs)
    return du
