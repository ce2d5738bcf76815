"""Tetrahedral meshes with region tags and node sets (geometry in millimetres)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np

__all__ = ["MeshError", "MeshQuality", "TetMesh", "boundary_faces", "mesh_quality"]

# Integer tags of the regions known to the toolkit; users may add more.
REGION_IDS: Mapping[str, int] = MappingProxyType({"bulk": 1, "inclusion": 2, "skin": 3})


class MeshError(ValueError):
    """A mesh that the solver cannot use (with the reason)."""


@dataclass(frozen=True)
class TetMesh:
    """A linear tetrahedral mesh.

    Parameters
    ----------
    nodes_mm : ndarray, shape (n_nodes, 3)
        Node coordinates in millimetres (phantom frame unless stated).
    tets : ndarray, shape (n_tets, 4)
        Node indices of each tetrahedron, positively oriented.
    region : ndarray, shape (n_tets,)
        Integer region tag per element (see ``region_names``).
    region_names : mapping of str to int
        Name of each region tag, e.g. ``{"bulk": 1, "inclusion": 2}``.
    node_sets : mapping of str to ndarray
        Named sets of node indices, e.g. ``"back"``, ``"surface"``, ``"nipple"``.
    """

    nodes_mm: np.ndarray
    tets: np.ndarray
    region: np.ndarray
    region_names: Mapping[str, int] = field(default_factory=lambda: {"bulk": 1})
    node_sets: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes_mm, dtype=float)
        tets = np.asarray(self.tets, dtype=np.int64)
        region = np.asarray(self.region, dtype=np.int64)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise MeshError(f"nodes must have shape (n, 3), got {nodes.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise MeshError(f"elements must be 4-node tetrahedra (m, 4), got {tets.shape}")
        if region.shape != (tets.shape[0],):
            raise MeshError(f"region needs one tag per element, got {region.shape}")
        if tets.size and (tets.min() < 0 or tets.max() >= len(nodes)):
            raise MeshError("element connectivity refers to nodes that do not exist")
        object.__setattr__(self, "nodes_mm", nodes)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "region", region)
        sets = {k: np.asarray(v, dtype=np.int64) for k, v in self.node_sets.items()}
        object.__setattr__(self, "node_sets", MappingProxyType(sets))
        object.__setattr__(self, "region_names", MappingProxyType(dict(self.region_names)))

    def __reduce__(self):
        # read-only mapping views do not pickle: rebuild them from plain dicts (a process
        # pool or a saved session carries meshes, calibrations with them)
        sets = dict(self.node_sets)
        return TetMesh, (self.nodes_mm, self.tets, self.region, dict(self.region_names), sets)

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return len(self.nodes_mm)

    @property
    def n_tets(self) -> int:
        """Number of tetrahedra."""
        return len(self.tets)

    def volumes_mm3(self) -> np.ndarray:
        """Signed element volumes in mm^3, shape (n_tets,)."""
        x = self.nodes_mm[self.tets]
        d = x[:, 1:] - x[:, :1]
        return np.linalg.det(d) / 6.0

    def node_set(self, name: str) -> np.ndarray:
        """The node indices of a named node set."""
        if name not in self.node_sets:
            raise KeyError(f"unknown node set {name!r}; mesh has {sorted(self.node_sets)}")
        return self.node_sets[name]

    def with_nodes(self, nodes_mm: np.ndarray) -> TetMesh:
        """The same topology, tags and sets on new node positions."""
        return replace(self, nodes_mm=np.asarray(nodes_mm, dtype=float))

    def with_node_sets(self, **sets: np.ndarray) -> TetMesh:
        """A copy with the given node sets added or replaced."""
        return replace(self, node_sets={**self.node_sets, **sets})

    def with_regions(self, region: np.ndarray, region_names: Mapping[str, int]) -> TetMesh:
        """A copy with new region tags."""
        return replace(self, region=region, region_names=region_names)

    def against_the_rest(self) -> np.ndarray:
        """Elements oriented against the rest: the smaller of the two orientations.

        Empty where every element has one orientation (either one). A recovered
        stress-free mesh may hold a few inverted at a clamped rim; a tangled mesh holds
        them elsewhere.

        Returns
        -------
        ndarray of int
            Element indices.
        """
        vol = self.volumes_mm3()
        neg, pos = np.flatnonzero(vol < 0), np.flatnonzero(vol > 0)
        if not (len(neg) and len(pos)):
            return neg[:0]
        return neg if len(neg) <= len(pos) else pos

    def oriented(self) -> TetMesh:
        """A copy with negatively oriented elements flipped; raises on degenerate ones.

        Returns
        -------
        TetMesh
            Same nodes (mm), node sets and regions; every element has positive volume.

        Raises
        ------
        MeshError
            Some element has zero volume (below ``1e-14`` times the cube of the mesh
            extent).
        """
        vol = self.volumes_mm3()
        scale = np.ptp(self.nodes_mm, axis=0).max() ** 3 if self.n_nodes else 1.0
        if np.any(np.abs(vol) <= 1e-14 * scale):
            bad = np.flatnonzero(np.abs(vol) <= 1e-14 * scale)
            raise MeshError(
                f"{bad.size} degenerate (zero-volume) elements, e.g. tetrahedron {bad[0]} "
                "(0-based, counting tetrahedra only)"
            )
        tets = self.tets.copy()
        neg = vol < 0
        tets[neg] = tets[neg][:, [0, 2, 1, 3]]
        return replace(self, tets=tets)


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tet mesh, outward oriented for positive tets.

    Parameters
    ----------
    tets : ndarray, shape (m, 4)

    Returns
    -------
    ndarray, shape (k, 3)
        Node indices of faces that belong to exactly one element.
    """
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


@dataclass(frozen=True)
class MeshQuality:
    """Quality figures of a tetrahedral mesh.

    Attributes
    ----------
    n_tets, n_nodes : int
    min_volume_mm3, max_volume_mm3 : float
    max_radius_edge_ratio : float
        Largest circumradius over shortest edge (sqrt(6)/4 = 0.612 for a regular tet).
    mean_radius_edge_ratio : float
        Mean of the same ratio over the elements (dimensionless).
    min_dihedral_deg, max_dihedral_deg : float
    n_inverted : int
        Elements with non-positive volume.
    n_slivers : int
        Elements with a dihedral angle below 5 or above 175 degrees.
    """

    n_tets: int
    n_nodes: int
    min_volume_mm3: float
    max_volume_mm3: float
    max_radius_edge_ratio: float
    mean_radius_edge_ratio: float
    min_dihedral_deg: float
    max_dihedral_deg: float
    n_inverted: int
    n_slivers: int

    @property
    def ok(self) -> bool:
        """True when no element is inverted or a sliver."""
        return self.n_inverted == 0 and self.n_slivers == 0


def _circumradius(x: np.ndarray) -> np.ndarray:
    a, b, c = (x[:, i] - x[:, 0] for i in (1, 2, 3))
    num = (
        (a**2).sum(1)[:, None] * np.cross(b, c)
        + (b**2).sum(1)[:, None] * np.cross(c, a)
        + (c**2).sum(1)[:, None] * np.cross(a, b)
    )
    den = 2.0 * np.einsum("ij,ij->i", a, np.cross(b, c))
    return np.linalg.norm(num, axis=1) / np.abs(den)


def _dihedral_angles_deg(x: np.ndarray) -> np.ndarray:
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    n = np.stack([np.cross(x[:, j] - x[:, i], x[:, k] - x[:, i]) for i, j, k in faces], axis=1)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    cos = np.stack([-(n[:, i] * n[:, j]).sum(1) for i, j in pairs], axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mesh_quality(mesh: TetMesh) -> MeshQuality:
    """Compute the quality figures of a mesh (see :class:`MeshQuality`)."""
    x = mesh.nodes_mm[mesh.tets]
    vol = mesh.volumes_mm3()
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    lmin = np.min([np.linalg.norm(x[:, i] - x[:, j], axis=1) for i, j in edges], axis=0)
    ratio = _circumradius(x) / lmin
    dih = _dihedral_angles_deg(x)
    return MeshQuality(
        n_tets=mesh.n_tets,
        n_nodes=mesh.n_nodes,
        min_volume_mm3=float(vol.min()),
        max_volume_mm3=float(vol.max()),
        max_radius_edge_ratio=float(ratio.max()),
        mean_radius_edge_ratio=float(ratio.mean()),
        min_dihedral_deg=float(dih.min()),
        max_dihedral_deg=float(dih.max()),
        n_inverted=int((vol <= 0).sum()),
        n_slivers=int(((dih < 5.0) | (dih > 175.0)).any(axis=1).sum()),
    )
