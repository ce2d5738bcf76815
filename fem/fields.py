"""Between solver vectors and model-frame quantities: loads, vertex and point displacements.

The solver works in metres in a rotated frame (``Discretization.R_solver_from_model``);
these helpers convert to and from the model frame in millimetres.
"""

from __future__ import annotations

import numpy as np

from .discretize import Discretization
from .units import M_PER_MM, MM_PER_M

__all__ = [
    "displacement_at",
    "edge_midpoint_displacement_mm",
    "gravity_vector",
    "vertex_displacement_mm",
]


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


def edge_midpoint_displacement_mm(
    disc: Discretization, x: np.ndarray, edges: np.ndarray
) -> np.ndarray:
    """Displacement at the midpoints of mesh edges (mm, model frame) from a solver vector.

    Exact for every formulation, without locating the points: a quadratic displacement
    (p2, taylor-hood) has its Lagrange degree of freedom at each edge's midpoint; a linear
    one (p1, and mini, whose bubble vanishes on the element's faces) takes the mean of the
    edge's two vertices.

    Parameters
    ----------
    disc : Discretization
    x : ndarray, shape (n_dofs,)
        ``Solution.state`` of a solve on ``disc``.
    edges : ndarray of int, shape (k, 2)
        Vertex pairs of ``disc.mesh``; each must be an edge of one of its tetrahedra.

    Returns
    -------
    ndarray, shape (k, 3)

    Raises
    ------
    ValueError
        A pair is not an edge of the mesh.
    """
    pairs = np.sort(np.asarray(edges, dtype=np.int64).reshape(-1, 2), axis=1)
    basis = disc.skfem_basis
    mesh_edges = np.sort(basis.mesh.edges.T, axis=1)  # (n_edges, 2), skfem's edge order
    key = mesh_edges[:, 0] * disc.mesh.n_nodes + mesh_edges[:, 1]
    order = np.argsort(key)
    wanted = pairs[:, 0] * disc.mesh.n_nodes + pairs[:, 1]
    at = np.minimum(np.searchsorted(key, wanted, sorter=order), len(key) - 1)
    found = key[order[at]] == wanted
    if not found.all():
        bad = pairs[np.flatnonzero(~found)[0]]
        raise ValueError(f"vertices {bad[0]} and {bad[1]} are not an edge of the mesh")
    edge = order[at]
    if basis.edge_dofs.size:  # the quadratic element's midpoint value
        u = x[: 3 * disc.n_scalar_u].reshape(-1, 3)[basis.edge_dofs[0, edge]]
        return u @ disc.R_solver_from_model * MM_PER_M
    vertex = vertex_displacement_mm(disc, x)
    return 0.5 * (vertex[pairs[:, 0]] + vertex[pairs[:, 1]])


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
