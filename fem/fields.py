"""Between solver vectors and model-frame quantities: loads, vertex and point displacements.

The solver works in metres in a rotated frame (``Discretization.R_solver_from_model``);
these helpers convert to and from the model frame in millimetres.
"""

from __future__ import annotations

import numpy as np

from .discretize import Discretization
from .units import M_PER_MM, MM_PER_M

__all__ = ["displacement_at", "gravity_vector", "vertex_displacement_mm"]


def gravity_vector(direction, g_m_s2: float) -> np.ndarray:
    """Gravity acceleration vector (m/s^2) from a direction (any length) and magnitude."""
    if not (np.isfinite(g_m_s2) and g_m_s2 >= 0):  # review AF: -9.81 turned gravity round
        raise ValueError(f"gravity's magnitude must be finite and >= 0 m/s^2, got {g_m_s2!r}")
    d = np.asarray(direction, dtype=float).reshape(3)
    if not np.all(np.isfinite(d)):
        raise ValueError(f"gravity direction must have finite components, got {d.tolist()}")
    # Scaled by its largest component first: a direction of 1e308s has no finite norm.
    big = np.max(np.abs(d))
    if g_m_s2 != 0 and big == 0:
        raise ValueError("gravity direction must be a non-zero vector")
    if big == 0:
        return np.zeros(3)
    d = d / big
    return d / np.linalg.norm(d) * g_m_s2


def vertex_displacement_mm(disc: Discretization, x: np.ndarray) -> np.ndarray:
    """Displacement of the mesh vertices in the model frame (mm) from a solver vector."""
    u = x[: 3 * disc.n_scalar_u].reshape(-1, 3)
    nodal = disc.skfem_basis.nodal_dofs[0]
    return u[nodal] @ disc.R_solver_from_model * MM_PER_M


def _point_forces(disc: Discretization, forces: dict | None) -> np.ndarray:
    f = np.zeros(disc.n_dofs)
    for node, force in (forces or {}).items():
        dof = 3 * disc.skfem_basis.nodal_dofs[0, node]
        f[dof : dof + 3] += disc.R_solver_from_model @ np.asarray(force, dtype=float)
    return f


def displacement_at(disc: Discretization, state: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Interpolate the FE displacement (full order of the formulation) at points.

    Parameters
    ----------
    disc : Discretization
    state : ndarray, shape (n_dofs,)
        ``Solution.state`` of a solve on ``disc``.
    points_mm : ndarray, shape (k, 3)
        Points inside the (undeformed) mesh, model frame, mm.

    Returns
    -------
    ndarray, shape (k, 3)
        Displacements in mm, model frame.
    """
    pts = (np.asarray(points_mm, float).reshape(-1, 3) * M_PER_MM) @ disc.R_solver_from_model.T
    try:
        P = disc.basis().probes(pts.T)
    except ValueError as exc:
        raise ValueError("a point to interpolate at lies outside the mesh") from exc
    u = state[: 3 * disc.n_scalar_u].reshape(-1, 3)
    return (P @ u) @ disc.R_solver_from_model * MM_PER_M
