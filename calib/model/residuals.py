"""Residuals of the calibration objectives and their derivatives in ``theta = ln c1``.

All geometry is in the reference frame (mm), i.e. the fiducial frame: no ICP.

- ``surface``: signed distance of each measured surface point (off the back plate) to
  the simulated deformed surface (without its back face). The model mesh's straight
  facets cut the chords of the reference scan's curved surface; a
  :meth:`SimulatedSurface.curved` surface carries that chord gap with the material (see
  there), a plain one (:meth:`SimulatedSurface.of`) does not.
- ``nipple``: signed distance of the simulated nipple node to the measured surface.
- ``landmarks``: simulated minus measured nipple and tumour centre (3 components each).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

import fem

from ..data.measurements import ScanMeasurement

__all__ = ["OBJECTIVES", "Residuals", "SimulatedSurface", "scan_residuals"]

OBJECTIVES = ("nipple", "surface", "landmarks")


def _scene(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, np.float32)),
        o3d.core.Tensor(np.asarray(faces, np.uint32)),
    )
    return scene


def surface_area_mm2(vertices_mm: np.ndarray, faces: np.ndarray) -> float:
    """Total area of the triangles ``faces`` (k, 3) over ``vertices_mm`` (n, 3), mm^2."""
    tri = np.asarray(vertices_mm, float)[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return 0.5 * float(np.linalg.norm(cross, axis=1).sum())


def closest_on_surface(vertices, faces, points, *, scene=None):
    """Closest points, triangle ids, barycentric weights (k, 3) and unit face normals.

    ``scene``: an open3d raycasting scene of ``(vertices, faces)`` built before, when the
    same surface is queried many times; None builds one.
    """
    import open3d as o3d

    scene = _scene(vertices, faces) if scene is None else scene
    ans = scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(float)
    w = np.column_stack([1.0 - uv.sum(1), uv[:, 0], uv[:, 1]])
    v = np.asarray(vertices, float)[faces[tri]]  # (k, 3, 3)
    closest = np.einsum("kc,kcj->kj", w, v)  # recomputed in double precision
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return closest, tri, w, n


@dataclass(frozen=True)
class SimulatedSurface:
    """Boundary triangles of the FE mesh without the back face (outward).

    Attributes
    ----------
    faces : ndarray of int, shape (f, 3)
    reference : tuple of ndarray or None
        For a curved surface (:meth:`curved`): the model mesh's reference node positions
        (n, 3), and the reference scan's surface vertices (m, 3) and faces (t, 3), all in
        the reference frame, mm; None for the straight facets.
    """

    faces: np.ndarray
    reference: tuple | None = None

    @classmethod
    def of(cls, mesh: fem.TetMesh) -> SimulatedSurface:
        """The outer surface of a mesh with a ``back`` node set."""
        faces = fem.boundary_faces(mesh.tets)
        back = np.zeros(mesh.n_nodes, bool)
        back[mesh.node_set("back")] = True
        return cls(faces[~back[faces].all(axis=1)])

    def curved(self, nodes_mm: np.ndarray, vertices_mm: np.ndarray, faces) -> SimulatedSurface:
        """The surface whose facets carry their gap to the reference scan's surface.

        A model mesh of ``h`` mm has straight facets, which cut the chords of the
        reference scan's curved surface (up to about ``h^2 / (8 R)`` inside it on a
        radius ``R``), and its corners come from a smoothed, remeshed copy of that
        surface. On the quick null twin's 14 mm mesh the gap has a mean of -0.096 mm and
        an sd of 0.157 mm (``diagnosis.json``'s ``model_mesh.facet_gap_mm``), as large as
        everything else in the residual of a posture near the reference. The gap belongs
        to the reference geometry, not to the mechanics: a residual at barycentrics ``w``
        of a deformed facet is corrected by the signed
        distance of the same material point of the reference facet from the reference
        scan's surface (:meth:`gap_mm`), along the deformed facet's normal (first order in
        the facet's rotation and stretch; the envelope theorem keeps the derivatives).

        Parameters
        ----------
        nodes_mm : ndarray, shape (n, 3)
            The model mesh's loaded reference geometry (reference frame, mm).
        vertices_mm : ndarray, shape (m, 3)
        faces : ndarray of int, shape (t, 3)
            The reference scan's surface (reference frame, outward).

        Returns
        -------
        SimulatedSurface
        """
        ref = (np.asarray(nodes_mm, float), np.asarray(vertices_mm, float), np.asarray(faces))
        return SimulatedSurface(self.faces, ref)

    def gap_mm(self, tri: np.ndarray, w: np.ndarray) -> np.ndarray:
        """The chord gap (mm, negative inside) at barycentrics ``w`` (k, 3) of facets ``tri``.

        The signed distance of those points of the reference facets from the reference
        scan's surface; zeros for straight facets.
        """
        if self.reference is None:
            return np.zeros(len(tri))
        nodes, vertices, faces = self.reference
        x = np.einsum("kc,kcj->kj", w, nodes[self.faces[tri]])
        c, _, _, n = closest_on_surface(vertices, faces, x, scene=self._reference_scene)
        return _signed(x - c, n)[0]

    def gap_at(self, points_mm: np.ndarray) -> np.ndarray:
        """The chord gap (mm, negative inside) at the reference facet points nearest ``points_mm``.

        ``points_mm`` (k, 3) in the reference frame: for instance the reference scan's own
        vertices, where the gap is what the straight facets miss of the scanned surface.
        """
        if self.reference is None:
            return np.zeros(len(points_mm))
        _, tri, w, _ = closest_on_surface(self.reference[0], self.faces, points_mm)
        return self.gap_mm(tri, w)

    @cached_property
    def _reference_scene(self):
        """The reference scan surface's raycasting scene, built once per curved surface."""
        _, vertices, faces = self.reference
        return _scene(vertices, faces)

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_reference_scene"}


@dataclass(frozen=True)
class Residuals:
    """Residuals ``r`` (mm) of one scan and ``dr/dtheta`` (mm per unit ln c1).

    Attributes
    ----------
    r : numpy.ndarray, shape (k,)
        The residuals, mm. ``surface``: signed distance of each measured point from the
        simulated surface (positive outside it), plus the chord gap of a curved
        :class:`SimulatedSurface`; ``nipple``: signed distance of the simulated nipple
        node from the measured surface (positive outside it), k = 1; ``landmarks``:
        simulated minus measured nipple, then tumour centre (where both are known), three
        components each (reference frame).
    dr : numpy.ndarray, shape (k,), or None
        ``dr/dtheta``, mm per unit ``ln c1``; None where no position derivatives were
        given.
    points_mm : numpy.ndarray, shape (k, 3)
        Where each residual lives, reference frame (the reference scan's LPS), mm: the
        measured surface points (``surface``), the simulated nipple node (``nipple``), or
        the simulated nipple and tumour centre, each repeated for its three components
        (``landmarks``). For maps and correlation lengths.
    """

    r: np.ndarray
    dr: np.ndarray | None
    points_mm: np.ndarray  # where each residual lives (for maps and correlation lengths)


def _signed(e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance ``|e|`` (sign of ``n . e``) and its unit direction.

    When the closest point lies on an edge or a vertex, ``e`` is not along the face
    normal; the direction of ``e`` (not ``n``) then gives the distance's derivative.
    """
    dist = np.linalg.norm(e, axis=1)
    sign = np.where(np.einsum("kj,kj->k", n, e) < 0, -1.0, 1.0)
    safe = dist > 1e-12
    u = np.where(safe[:, None], e / np.where(safe, dist, 1.0)[:, None], n)
    return sign * dist, sign[:, None] * u


def _surface(sim: SimulatedSurface, pos, dpos, points) -> Residuals:
    c, tri, w, n = closest_on_surface(pos, sim.faces, points)
    r, u = _signed(points - c, n)
    r = r + sim.gap_mm(tri, w)  # the curved surface lies -gap outside the facet
    dr = None
    if dpos is not None:  # envelope theorem: the closest point's barycentrics stay fixed
        dc = np.einsum("kc,kcj->kj", w, dpos[sim.faces[tri]])
        dr = -np.einsum("kj,kj->k", u, dc)
    return Residuals(r, dr, points)


def _nipple(meas: ScanMeasurement, nipple_node: int, pos, dpos) -> Residuals:
    p = pos[nipple_node][None]
    faces = meas.faces[meas.in_view[meas.faces].any(axis=1)]  # not a cut field of view's
    c, _, _, n = closest_on_surface(meas.vertices_mm, faces, p)
    r, u = _signed(p - c, n)
    dr = None if dpos is None else np.einsum("kj,kj->k", u, dpos[nipple_node][None])
    return Residuals(r, dr, p)


def _landmarks(meas: ScanMeasurement, nipple_node, tumour, pos, dpos) -> Residuals:
    """``tumour`` is ``(p, dp)`` of the simulated tumour centre, or None."""
    p_n = pos[nipple_node]
    r = [p_n - meas.nipple_mm]
    dr = [None if dpos is None else dpos[nipple_node]]
    pts = [p_n]
    if tumour is not None and meas.tumour_mm is not None:
        r.append(tumour[0] - meas.tumour_mm)
        dr.append(tumour[1])
        pts.append(tumour[0])
    drv = None if dpos is None else np.concatenate(dr)
    return Residuals(np.concatenate(r), drv, np.repeat(np.array(pts), 3, axis=0))


def scan_residuals(
    objective: str,
    meas: ScanMeasurement,
    mesh: fem.TetMesh,
    sim: SimulatedSurface,
    positions_mm: np.ndarray,
    dpositions_mm: np.ndarray | None,
    *,
    surface_points_mm: np.ndarray,
    tumour=None,
) -> Residuals:
    """Residuals of one scan for an objective (see the module docstring)."""
    nipple = int(mesh.node_set("nipple")[0])
    if objective == "surface":
        return _surface(sim, positions_mm, dpositions_mm, surface_points_mm)
    if objective == "nipple":
        return _nipple(meas, nipple, positions_mm, dpositions_mm)
    if objective == "landmarks":
        return _landmarks(meas, nipple, tumour, positions_mm, dpositions_mm)
    raise ValueError(f"unknown objective {objective!r}; choose from {OBJECTIVES}")
