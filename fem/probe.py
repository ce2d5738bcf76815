"""Material points: follow a point of the body (a tumour centre, a marker) through solves.

A material point is fixed by the element that contains it and its barycentric
coordinates there. Elements are affine, so these coordinates do not change when the
nodes move: the point's position in any configuration of the same mesh (the loaded
scan, the recovered stress-free geometry) is the barycentric mix of that element's
vertices, and its displacement is the formulation's full-order interpolation of the
solver state at the same coordinates (P2 for Taylor-Hood).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp

from .discretize import Discretization, _skfem_mesh
from .units import MM_PER_M, mm_to_m

__all__ = ["MaterialPoint", "contains", "nearest_inside_mm"]


@dataclass(frozen=True)
class MaterialPoint:
    """A point of the body, followed by its barycentric coordinates.

    Attributes
    ----------
    vertex_weights : scipy.sparse.csr_matrix, shape (1, n_nodes)
        Barycentric weights on the mesh vertices (4 non-zeros).
    shape_weights : scipy.sparse.csr_matrix, shape (1, n_scalar_u)
        Values of the displacement shape functions at the point.
    R_solver_from_model : ndarray, shape (3, 3)
        The discretization's rotation (solver vectors are in its frame, metres).
    """

    vertex_weights: sp.csr_matrix
    shape_weights: sp.csr_matrix
    R_solver_from_model: np.ndarray

    @classmethod
    def locate(
        cls,
        disc: Discretization,
        point_mm: np.ndarray,
        *,
        outside: Literal["raise", "nearest"] = "raise",
    ) -> MaterialPoint:
        """The material point at ``point_mm`` of ``disc.mesh``'s current geometry.

        Parameters
        ----------
        disc : Discretization
            Of the mesh in the configuration where ``point_mm`` is given.
        point_mm : array_like, shape (3,)
            Model frame, mm.
        outside : {"raise", "nearest"}
            A point outside the mesh raises, or is taken at the nearest point inside
            (:func:`nearest_inside_mm`; a coarse model surface cuts the body's curved
            surface, and a point just under it can lie outside): compare
            :meth:`place_mm` of the mesh's nodes with ``point_mm`` to know how far.

        Raises
        ------
        ValueError
            The point lies outside the mesh (``outside="raise"``).
        """
        from skfem import Basis, ElementTetP1

        R = disc.R_solver_from_model
        p1 = Basis(_skfem_mesh(disc.mesh, R), ElementTetP1(), intorder=1)

        def at(point: np.ndarray) -> MaterialPoint:
            pts = mm_to_m(np.asarray(point, float).reshape(1, 3)) @ R.T
            return cls(
                sp.csr_matrix(p1.probes(pts.T)), sp.csr_matrix(disc.basis().probes(pts.T)), R
            )

        try:
            return at(point_mm)
        except ValueError as exc:
            if outside != "nearest":
                raise ValueError(
                    f"material point {np.ravel(point_mm)} lies outside the mesh"
                ) from exc
        return at(nearest_inside_mm(disc.mesh, point_mm))

    def place_mm(self, nodes_mm: np.ndarray) -> np.ndarray:
        """Position (mm) of the point in a configuration of the mesh's vertices, (3,)."""
        return np.asarray(self.vertex_weights @ nodes_mm)[0]

    def displacement_mm(self, state: np.ndarray) -> np.ndarray:
        """Displacement (mm, model frame) of the point from a solver state, (3,)."""
        n = self.shape_weights.shape[1]
        u = np.asarray(state[: 3 * n]).reshape(-1, 3)
        return np.asarray(self.shape_weights @ u)[0] @ self.R_solver_from_model * MM_PER_M

    def position_mm(self, nodes_mm: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Current position (mm): the point in ``nodes_mm`` plus its displacement, (3,).

        By linearity the same call maps derivatives: ``position_mm(dX, dstate)`` is the
        derivative of the position when the nodes and the state have derivatives
        ``dX`` and ``dstate``.
        """
        return self.place_mm(nodes_mm) + self.displacement_mm(state)


def contains(mesh, point_mm: np.ndarray) -> bool:
    """Whether a point (model frame, mm) lies in the mesh.

    As :meth:`MaterialPoint.locate` finds it: skfem's element finder on the mesh in
    metres, the same test and tolerance.

    Parameters
    ----------
    mesh : TetMesh
    point_mm : array_like, shape (3,)
    """
    finder = _skfem_mesh(mesh, np.eye(3)).element_finder()
    p = mm_to_m(np.asarray(point_mm, float).reshape(3, 1))
    try:
        finder(*p)
    except ValueError:
        return False
    return True


def nearest_inside_mm(mesh, point_mm: np.ndarray, *, candidates: int = 32) -> np.ndarray:
    """``point_mm`` where it lies in one of the candidate tetrahedra, else the nearest point inside.

    Meant for a point outside the mesh (:meth:`MaterialPoint.locate` calls it only then):
    the candidates are the elements nearest by centroid, which in a strongly graded mesh
    need not hold an inside point's own element.

    The nearest point of each of the ``candidates`` tetrahedra with the nearest centroids
    (non-negative least squares for its barycentric coordinates, their sum held at 1 by a
    heavily weighted row), moved a millionth of the way to that element's centroid so that
    it lies strictly inside.

    Parameters
    ----------
    mesh : fem.TetMesh
    point_mm : array_like, shape (3,)
        Model frame, mm.
    candidates : int
        Elements tried.

    Returns
    -------
    ndarray, shape (3,)
    """
    from scipy.optimize import nnls
    from scipy.spatial import cKDTree

    p = np.asarray(point_mm, float).reshape(3)
    X = mesh.nodes_mm[mesh.tets]  # (n_tets, 4, 3)
    centroid = X.mean(axis=1)
    _, near = cKDTree(centroid).query(p, k=min(candidates, len(X)))
    best, best_d = p, np.inf
    for t in np.atleast_1d(near):
        T = (X[t, 1:] - X[t, 0]).T
        lam = np.linalg.solve(T, p - X[t, 0])
        bary = np.r_[1.0 - lam.sum(), lam]
        if np.all(bary >= 0.0):
            return p  # inside
        w = 1e4 * max(float(np.ptp(X[t], axis=0).max()), 1e-9)
        bary, _ = nnls(np.vstack([X[t].T, np.full(4, w)]), np.r_[p, w])
        q = (bary / bary.sum()) @ X[t]
        d = float(np.linalg.norm(q - p))
        if d < best_d:
            best, best_d = q + 1e-6 * (centroid[t] - q), d
    return best
