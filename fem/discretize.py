"""Finite element spaces, quadrature data and the sparsity pattern of a mesh.

A :class:`Discretization` holds everything that depends on the mesh, the
formulation and the support but not on the material or the load, so one
discretization serves every solve of a calibration or a gravity sweep.
Internally lengths are in metres and the back plane's outward normal is -z
(the "solver frame"); conversions happen here and in :mod:`fem.solver`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import scipy.sparse as sp

from .mesh import MeshError, TetMesh
from .model import Clamped, Constrained, ElasticSupport, Sliding, Support, as_supports
from .pattern import Pattern, build_pattern
from .units import M_PER_MM

__all__ = [
    "FORMULATIONS",
    "Discretization",
    "Formulation",
    "discretize",
    "plane_fit",
    "spring_shape_derivative",
]

Formulation = Literal["p1", "p2", "mini", "taylor-hood"]
# name -> (displacement element, pressure element or None, quadrature order)
FORMULATIONS = {
    "p1": ("ElementTetP1", None, 1),
    "p2": ("ElementTetP2", None, 2),
    "mini": ("ElementTetMini", "ElementTetP1", 4),
    "taylor-hood": ("ElementTetP2", "ElementTetP1", 2),
}


@dataclass(frozen=True)
class Discretization:
    """Mesh-dependent data of one formulation (see module docstring for frames).

    ``E`` elements, ``Q`` quadrature points per element, ``Au`` displacement and ``Ap``
    pressure shape functions per element. The full unknown vector (``n_dofs``) holds the
    displacements node-major (``3 * scalar dof + component``, solver frame, m), then the
    pressures (Pa).

    Attributes
    ----------
    mesh : TetMesh
        The mesh the data belong to, model frame, mm (in a copy made by
        :meth:`with_nodes`, on the moved nodes).
    formulation : {"p1", "p2", "mini", "taylor-hood"}
    R_solver_from_model : numpy.ndarray, shape (3, 3)
        Rotation from the model frame to the solver frame: a plane support's outward
        normal goes to -z; the identity without a plane support.
    grad_u : numpy.ndarray, shape (E, Q, Au, 3)
        Gradients of the displacement shape functions at the quadrature points, with
        respect to the mesh's (undeformed) coordinates, solver frame, 1/m.
    shape_u : numpy.ndarray, shape (E, Q, Au)
        Values of the displacement shape functions at the quadrature points.
    shape_p : numpy.ndarray, shape (E, Q, Ap), or None
        Values of the pressure shape functions; None for ``p1`` and ``p2``.
    weights : numpy.ndarray, shape (E, Q)
        Quadrature weights times ``|det J|``, m^3.
    udofs : numpy.ndarray of int, shape (E, Au)
        Scalar displacement dof of each element's shape functions.
    pdofs : numpy.ndarray of int, shape (E, Ap), or None
        Pressure dof of each element's pressure functions (offset by ``3 * n_scalar_u``
        in the full vector); None for ``p1`` and ``p2``.
    n_scalar_u : int
        Scalar displacement dofs (three unknowns each).
    n_p : int
        Pressure dofs (0 for ``p1`` and ``p2``).
    fixed : numpy.ndarray of bool, shape (n_dofs,)
        The Dirichlet (support) unknowns of the full vector.
    pattern : Pattern
        Sparsity of the reduced (free-unknown) matrix and the scatter map into it.
    spring : scipy.sparse.csr_matrix, shape (n_dofs, n_dofs), or None
        Summed spring matrix of the supports with springs, N/m (solver frame); None
        without springs.
    skfem_basis : skfem.Basis
        Scalar displacement basis on the nodes given to :func:`discretize` (solver frame,
        m; not moved by :meth:`with_nodes`: :meth:`basis` is on the current nodes).
    spring_faces : tuple of (numpy.ndarray, Support)
        The scikit-fem boundary facets and the support of every support with springs;
        their matrix is assembled again on the current nodes by :meth:`with_nodes`.
    """

    mesh: TetMesh
    formulation: str
    R_solver_from_model: np.ndarray  # (3, 3)
    grad_u: np.ndarray  # (E, Q, Au, 3) reference gradients of displacement shape functions, 1/m
    shape_u: np.ndarray  # (E, Q, Au)
    shape_p: np.ndarray | None  # (E, Q, Ap)
    weights: np.ndarray  # (E, Q) quadrature weights times |det J|, m^3
    udofs: np.ndarray  # (E, Au) scalar displacement dofs
    pdofs: np.ndarray | None  # (E, Ap) pressure dofs
    n_scalar_u: int
    n_p: int
    fixed: np.ndarray  # (n_dofs,) bool, Dirichlet dofs of the full vector
    pattern: Pattern
    spring: sp.csr_matrix | None  # full-size spring matrix of an elastic support, N/m
    skfem_basis: object  # scalar displacement basis (for probes and cross-checks)
    # (facets, support) of every support with springs: their matrix is assembled on the
    # current nodes (springs act per unit stress-free area), again by with_nodes
    spring_faces: tuple = ()

    @property
    def mixed(self) -> bool:
        """True for displacement-pressure formulations."""
        return self.shape_p is not None

    @property
    def n_dofs(self) -> int:
        """Size of the full unknown vector (3 per displacement dof, plus pressures)."""
        return 3 * self.n_scalar_u + self.n_p

    @property
    def free(self) -> np.ndarray:
        """Indices of the unknowns that are solved for."""
        return np.flatnonzero(~self.fixed)

    def element_dofs(self) -> np.ndarray:
        """Global dofs of each element, shape (E, 3 Au + Ap), u (node-major) then p."""
        u = (3 * self.udofs[:, :, None] + np.arange(3)).reshape(len(self.udofs), -1)
        if not self.mixed:
            return u
        return np.hstack([u, 3 * self.n_scalar_u + self.pdofs])

    def with_nodes(self, nodes_mm: np.ndarray) -> Discretization:
        """Same topology, support and pattern on moved nodes (for reference recovery).

        Elements are affine, so the new gradients and weights follow from the
        reference-element data and the new vertex positions alone (no re-initialisation).
        A support's springs act per unit area of the face on the new nodes and are
        assembled there again.
        """
        mesh = self.mesh.with_nodes(nodes_mm)
        jac = _jacobians(mesh, self.R_solver_from_model)
        ref = self.reference_data
        grad = np.einsum("qam,emj->eqaj", ref["grad"], np.linalg.inv(jac), optimize=True)
        weights = np.abs(np.linalg.det(jac))[:, None] * ref["weights"][None, :]
        moved = replace(self, mesh=mesh, grad_u=grad, weights=weights)
        if not self.spring_faces:
            return moved
        # the support's springs act per unit area of the face on these nodes: a face that
        # stretches in its plane (a sliding back) carries more spring force
        basis = moved.basis()
        return replace(moved, spring=_springs(basis, self.spring_faces, self.n_dofs))

    def basis(self):
        """A scikit-fem basis of the displacement space on the current nodes."""
        from skfem import Basis

        b = self.skfem_basis
        p = (self.mesh.nodes_mm * M_PER_MM) @ self.R_solver_from_model.T
        if np.array_equal(b.mesh.p, p.T):
            return b
        return Basis(
            _skfem_mesh(self.mesh, self.R_solver_from_model), b.elem, quadrature=b.quadrature
        )

    @property
    def reference_data(self) -> dict:
        """Reference-element gradients (Q, Au, 3) and quadrature weights (Q,)."""
        return _reference_data(self.skfem_basis)


def _jacobians(mesh: TetMesh, R: np.ndarray) -> np.ndarray:
    """Affine element maps ``[x1-x0, x2-x0, x3-x0]`` (columns), solver frame, m; (E, 3, 3)."""
    x = (mesh.nodes_mm[mesh.tets] * M_PER_MM) @ R.T
    return np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)


def _reference_data(basis) -> dict:
    """Reference gradients and weights from a basis built on its own (undeformed) mesh."""
    m = basis.mesh
    p, t = m.p.T, m.t.T
    jac0 = np.stack([p[t[0, 1]] - p[t[0, 0]], p[t[0, 2]] - p[t[0, 0]], p[t[0, 3]] - p[t[0, 0]]], 1)
    grads = np.stack([phi[0].grad[:, 0] for phi in basis.basis], axis=0)  # (Au, 3, Q)
    grad_ref = np.einsum("ajq,jm->qam", grads, jac0)
    return {"grad": grad_ref, "weights": np.asarray(basis.dx[0]) / abs(np.linalg.det(jac0))}


def plane_fit(points_mm: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares plane through points: unit normal, offset (n.x = d) and RMS error in mm."""
    c = points_mm.mean(axis=0)
    _, s, vt = np.linalg.svd(points_mm - c, full_matrices=False)
    n = vt[-1]
    return n, float(n @ c), float(s[-1] / np.sqrt(len(points_mm)))


def _rotation_to_minus_z(n: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector ``n`` to (0, 0, -1)."""
    t = np.array([0.0, 0.0, -1.0])
    v, c = np.cross(n, t), float(n @ t)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _outward_back_normal(mesh: TetMesh, support) -> np.ndarray:
    back = mesh.node_set(support.node_set)
    if len(back) < 3:
        raise MeshError(f"node set {support.node_set!r} has {len(back)} nodes; need >= 3")
    n, d, _ = plane_fit(mesh.nodes_mm[back])
    if mesh.nodes_mm.mean(axis=0) @ n > d:  # body lies on the +n side: flip outward
        n = -n
    return n


def _skfem_mesh(mesh: TetMesh, R: np.ndarray):
    from skfem import MeshTet

    p = (mesh.nodes_mm * M_PER_MM) @ R.T
    return MeshTet(np.ascontiguousarray(p.T), np.ascontiguousarray(mesh.tets.T), sort_t=False)


def _element(name: str):
    import skfem

    return getattr(skfem, name)()


def _geometry(mesh: TetMesh, formulation: str, R: np.ndarray) -> dict:
    from skfem import Basis

    eu, ep, order = FORMULATIONS[formulation]
    m = _skfem_mesh(mesh, R)
    bu = Basis(m, _element(eu), intorder=order)
    grads = np.stack([phi[0].grad for phi in bu.basis], axis=0)  # (Au, 3, E, Q)
    vals = np.stack([np.asarray(phi[0]) for phi in bu.basis], axis=0)  # (Au, E, Q)
    geo = {
        "grad_u": np.ascontiguousarray(grads.transpose(2, 3, 0, 1)),
        "shape_u": np.ascontiguousarray(vals.transpose(1, 2, 0)),
        "weights": np.asarray(bu.dx),
        "skfem_basis": bu,
        "shape_p": None,
    }
    if ep is not None:
        bp = Basis(m, _element(ep), quadrature=bu.quadrature)
        pv = np.stack([np.asarray(phi[0]) for phi in bp.basis], axis=0)
        geo["shape_p"] = np.ascontiguousarray(pv.transpose(1, 2, 0))
    return geo


def _dofs(mesh: TetMesh, formulation: str) -> dict:
    from skfem import Basis

    eu, ep, _ = FORMULATIONS[formulation]
    m = _skfem_mesh(mesh, np.eye(3))
    bu = Basis(m, _element(eu), intorder=1)
    out = {"udofs": bu.element_dofs.T.copy(), "n_scalar_u": bu.N, "pdofs": None, "n_p": 0}
    if ep is not None:
        bp = Basis(m, _element(ep), intorder=1)
        out.update(pdofs=bp.element_dofs.T.copy(), n_p=bp.N)
    return out


def _face_dofs(basis, mesh: TetMesh, node_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scalar dofs on the boundary facets whose nodes all lie in ``node_ids``; and the facets."""
    m = basis.mesh
    bf = m.boundary_facets()
    inset = np.zeros(mesh.n_nodes, dtype=bool)
    inset[node_ids] = True
    facets = bf[inset[m.facets[:, bf]].all(axis=0)]
    if facets.size == 0:
        raise MeshError("the support's node set contains no boundary face")
    return np.unique(basis.get_dofs(facets=facets).flatten()), facets


def _rim_nodes(facets_nodes: np.ndarray) -> np.ndarray:
    """Nodes on the boundary edges of a set of triangles (edges used by one triangle)."""
    e = np.sort(facets_nodes[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return np.unique(uniq[counts == 1])


def _constrained_dofs(basis, mesh: TetMesh, support: Constrained) -> np.ndarray:
    """Scalar dofs of a constrained node set: its vertices and P2 edges among them."""
    nodes = mesh.node_set(support.node_set)
    dofs = [basis.nodal_dofs[0, nodes]]
    if basis.edge_dofs.size:
        dofs.append(basis.edge_dofs[0, np.isin(basis.mesh.edges, nodes).all(axis=0)])
    return np.unique(np.concatenate(dofs))


def _support_dofs(basis, mesh: TetMesh, support: Support, fixed: np.ndarray):
    """Mark the support's fixed dofs (solver frame, back normal -z); return its facets."""
    if isinstance(support, Constrained):
        sdofs = _constrained_dofs(basis, mesh, support)
        for c in support.components:
            fixed[3 * sdofs + c] = True
        return None
    sdofs, facets = _face_dofs(basis, mesh, mesh.node_set(support.node_set))
    if isinstance(support, Clamped):
        for c in range(3):
            fixed[3 * sdofs + c] = True
    elif isinstance(support, Sliding):
        fixed[3 * sdofs + 2] = True
        if support.hold == "rim":
            rim = _rim_nodes(basis.mesh.facets[:, facets].T)
            rim_dofs = _rim_dofs(basis, rim, sdofs)
            fixed[3 * rim_dofs] = True
            fixed[3 * rim_dofs + 1] = True
    return facets


def _rim_dofs(basis, rim_nodes: np.ndarray, face_dofs: np.ndarray) -> np.ndarray:
    """Scalar dofs at rim vertices and on rim edges (P2 midside dofs) of the face."""
    m = basis.mesh
    dofs = [basis.nodal_dofs[0, rim_nodes]]
    if basis.edge_dofs.size:
        on_rim = np.isin(m.edges, rim_nodes).all(axis=0)
        dofs.append(np.intersect1d(basis.edge_dofs[0, on_rim], face_dofs))
    return np.unique(np.concatenate(dofs))


def _face_mass():
    from skfem import BilinearForm

    @BilinearForm
    def mass(u, v, _):
        return u * v

    return mass


def _spring_diagonal(support: Support) -> np.ndarray:
    """Spring stiffness per area along the solver axes (back normal z), (3,), N/m^3."""
    if isinstance(support, ElasticSupport):
        kn, kt = support.normal_stiffness_pa_per_mm, support.tangent_stiffness_pa_per_mm
    else:  # Sliding on tangential springs: the normal is fixed, not sprung
        kn, kt = 0.0, support.tangent_stiffness_pa_per_mm
    return np.array([kt, kt, kn]) / M_PER_MM


def _spring_matrix(basis, facets, support: Support, n_total: int) -> sp.csr_matrix:
    """Node-major spring matrix ``M (x) S`` of one support's face (N/m), full size."""
    from skfem import FacetBasis

    fb = FacetBasis(basis.mesh, basis.elem, facets=facets)
    M = _face_mass().assemble(fb)
    S = sp.csr_matrix(np.diag(_spring_diagonal(support)))  # back normal is z (solver frame)
    K = sp.kron(M, S, format="csr")
    K.resize((n_total, n_total))
    return K.tocsr()


def discretize(
    mesh: TetMesh, support: Support, *, formulation: Formulation = "taylor-hood"
) -> Discretization:
    """Build the finite element data of a mesh for one formulation and support.

    Parameters
    ----------
    mesh : TetMesh
        Positively oriented linear tets, nodes in mm, with the support's node set.
    support : Clamped, Sliding or ElasticSupport
        Boundary condition of the back plane.
    formulation : {"p1", "p2", "mini", "taylor-hood"}
        Displacement P1 or P2, or mixed displacement-pressure MINI (P1+bubble/P1)
        or Taylor-Hood (P2/P1), the locking-free choices for nearly
        incompressible material.

    Returns
    -------
    Discretization

    Raises
    ------
    ValueError
        ``formulation`` is unknown, or ``Constrained`` node sets are combined with a
        sliding/elastic plane.
    MeshError
        The mesh has inverted or degenerate elements, or a plane support's node set has
        fewer than 3 nodes or no boundary face.
    """
    if formulation not in FORMULATIONS:
        raise ValueError(f"unknown formulation {formulation!r}; choose {sorted(FORMULATIONS)}")
    if np.any(mesh.volumes_mm3() <= 0):
        raise MeshError("mesh has inverted or degenerate elements; call TetMesh.oriented()")
    supports = as_supports(support)
    R = _solver_rotation(mesh, supports)
    geo = _geometry(mesh, formulation, R)
    dofs = _dofs(mesh, formulation)
    n_total = 3 * dofs["n_scalar_u"] + dofs["n_p"]
    fixed = np.zeros(n_total, dtype=bool)
    faces = []
    for sup in supports:
        facets = _support_dofs(geo["skfem_basis"], mesh, sup, fixed)
        if _has_springs(sup):
            faces.append((facets, sup))
    disc = Discretization(
        mesh=mesh,
        formulation=formulation,
        R_solver_from_model=R,
        fixed=fixed,
        pattern=None,  # type: ignore[arg-type]
        spring=_springs(geo["skfem_basis"], faces, n_total),
        spring_faces=tuple(faces),
        **geo,
        **dofs,
    )
    return replace(disc, pattern=build_pattern(disc.udofs, disc.pdofs, disc.n_scalar_u, fixed))


def _solver_rotation(mesh: TetMesh, supports: tuple) -> np.ndarray:
    """Rotation making the plane support's outward normal -z; identity when not needed."""
    planar = [s for s in supports if isinstance(s, (Sliding, ElasticSupport))]
    if any(isinstance(s, Constrained) for s in supports) and planar:
        raise ValueError("Constrained node sets cannot be combined with a sliding/elastic plane")
    return _rotation_to_minus_z(_outward_back_normal(mesh, planar[0])) if planar else np.eye(3)


def _has_springs(support: Support) -> bool:
    return isinstance(support, ElasticSupport) or (
        isinstance(support, Sliding) and support.tangent_stiffness_pa_per_mm > 0
    )


def _springs(basis, faces, n_total: int) -> sp.csr_matrix | None:
    """The summed spring matrix of ``faces`` ((facets, support) pairs), None without any."""
    spring = None
    for facets, sup in faces:
        K = _spring_matrix(basis, facets, sup, n_total)
        spring = K if spring is None else spring + K
    return spring


def _facet_normals(p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (n_facets, 3) and areas (n_facets,) of triangles ``tri`` of points ``p``."""
    P = p[:, tri]  # (3, 3 corners, n_facets)
    N = np.cross((P[:, 1] - P[:, 0]).T, (P[:, 2] - P[:, 0]).T)
    twice_area = np.linalg.norm(N, axis=1)
    return N / twice_area[:, None], 0.5 * twice_area


def spring_shape_derivative(disc: Discretization, x: np.ndarray) -> sp.csr_matrix | None:
    """``d(K_s(X) x)/dX`` of a support's springs, full size (vertex columns), N/m.

    The springs act per unit area of the stress-free face: on a straight facet the P2
    mass matrix is ``M_f = A_f Mhat``, so the facet's force ``c_f = (M_f (x) S) x_f``
    moves with the area as ``dc_f = (c_f / A_f) dA_f``, with (triangle ``p0 p1 p2``, unit
    normal ``n``) ``dA/dp0 = (p1 - p2) x n / 2`` and cyclically. Columns ``3 v + m`` are
    the ``m``-th solver coordinate (m) of vertex ``v``'s displacement unknown, as in
    :func:`fem.shape_derivative.geometry_matrices`. None without springs.

    Parameters
    ----------
    disc : Discretization
        On the stress-free nodes.
    x : ndarray, shape (n_dofs,)
        State (solver frame, SI).
    """
    if not disc.spring_faces:
        return None
    from skfem import FacetBasis

    # the facet mass per unit area is the same on any straight facet: it comes from the
    # basis as built (no basis on the current nodes), the areas' derivative from the
    # current nodes
    basis = disc.skfem_basis
    p0 = basis.mesh.p  # (3, n_vertices), solver frame, m
    p = ((disc.mesh.nodes_mm * M_PER_MM) @ disc.R_solver_from_model.T).T
    rows, cols, vals = [], [], []
    for facets, sup in disc.spring_faces:
        fb = FacetBasis(basis.mesh, basis.elem, facets=facets)
        coo = _face_mass().coo_data(fb)
        nb = coo.local_shape[0]
        M = coo.data.reshape(nb, nb, -1)  # (a, b, facet)
        dofs = fb.element_dofs  # (nb, n_facets) scalar dofs of the owning elements
        S = _spring_diagonal(sup)
        xs = x[: 3 * disc.n_scalar_u].reshape(-1, 3)[dofs]  # (nb, n_facets, 3)
        c = np.einsum("abf,bfi->afi", M, xs) * S  # (a, facet, i), N
        tri = basis.mesh.facets[:, facets]  # (3, n_facets) vertex ids
        c_per_area = c / _facet_normals(p0, tri)[1][None, :, None]
        P = p[:, tri].transpose(1, 2, 0)  # (3 corners, n_facets, 3)
        n = _facet_normals(p, tri)[0]
        dA = 0.5 * np.stack([np.cross(P[(k + 1) % 3] - P[(k + 2) % 3], n) for k in range(3)])
        vdof = basis.nodal_dofs[0][tri]  # (3, n_facets) scalar dof of each corner
        # entry (a, i, k, m): row 3 dofs[a] + i, column 3 vdof[k] + m
        r = (3 * dofs)[:, None, None, None, :] + np.arange(3)[None, :, None, None, None]
        q = (3 * vdof)[None, None, :, None, :] + np.arange(3)[None, None, None, :, None]
        v = (
            c_per_area.transpose(0, 2, 1)[:, :, None, None, :]
            * dA.transpose(0, 2, 1)[None, None, :, :, :]
        )
        shape = (nb, 3, 3, 3, len(facets))
        rows.append(np.broadcast_to(r, shape).ravel())
        cols.append(np.broadcast_to(q, shape).ravel())
        vals.append(np.broadcast_to(v, shape).ravel())
    n = disc.n_dofs
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
