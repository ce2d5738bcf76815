"""Tetrahedral meshing with TetGen, automatic surface repair, tags and node sets."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .discretize import plane_fit
from .geometry import Phantom, sphere_surface
from .mesh import REGION_IDS, MeshError, TetMesh, boundary_faces

__all__ = [
    "append_spheres",
    "check_max_dihedral_deg",
    "find_back_plane",
    "inclusion_spheres",
    "mesh_phantom",
    "remesh_surface",
    "subtet_centroids",
    "surface_defects",
    "tag_node_sets",
    "tetrahedralize",
]

log = logging.getLogger(__name__)


#: Debug files TetGen writes into the working directory when it skips input faces.
_TETGEN_LITTER = ("_skipped.face", "_skipped.node")


def check_max_dihedral_deg(value: float | None, name: str = "max_dihedral_deg") -> None:
    """Raise ``ValueError`` unless ``value`` is None or a dihedral bound in (90, 180) degrees.

    ``name`` is what the message calls it (an option's own name).
    """
    if value is not None and not 90.0 < value < 180.0:
        raise ValueError(f"{name} must lie in (90, 180) degrees, got {value}")


def _tetgen(vertices, faces, max_volume, min_ratio, min_dihedral, regions, max_dihedral=None):
    import tetgen

    litter = [Path(name) for name in _TETGEN_LITTER if not Path(name).exists()]
    tg = tetgen.TetGen(np.asarray(vertices, float), np.asarray(faces, np.int32))
    for tag, point, *vol in regions:  # (tag, point[, max volume mm^3])
        tg.add_region(int(tag), np.asarray(point, float), float(vol[0]) if vol else -1.0)
    sized = any(len(r) > 2 for r in regions)
    try:
        nodes, tets, attrib, _ = tg.tetrahedralize(
            quality=True,
            minratio=min_ratio,
            mindihedral=min_dihedral,
            maxvolume=max_volume if max_volume else -1.0,
            fixedvolume=bool(max_volume),
            varvolume=sized,
            regionattrib=bool(regions),
            **({} if max_dihedral is None else {"optmaxdihedral": float(max_dihedral)}),
        )
    finally:  # never leave TetGen's debug files in the user's folder
        for path in litter:
            if path.exists():
                log.info("TetGen skipped input faces (its %s is removed)", path)
                path.unlink(missing_ok=True)
    region = attrib[:, 0].astype(int) if regions else np.full(len(tets), REGION_IDS["bulk"])
    region[region == 0] = REGION_IDS["bulk"]  # TetGen's attribute of a region not seeded
    return nodes, tets, region


def _repair_surface(vertices, faces):
    """Merge duplicates, drop degenerate faces, fix winding and fill small holes."""
    import trimesh

    m = trimesh.Trimesh(vertices, faces, process=True)
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    trimesh.repair.fill_holes(m)
    trimesh.repair.fix_normals(m)
    return np.asarray(m.vertices), np.asarray(m.faces)


def remesh_surface(vertices, faces, *, size_mm: float, grid_mm: float | None = None):
    """Rebuild a clean, closed, manifold surface from a possibly self-intersecting one.

    The inside is sampled on a grid (majority of ray-parity votes, robust to
    self-intersections), then marching cubes, Taubin smoothing and decimation to about
    the face count of edges of ``size_mm``. The grid step ``grid_mm`` defaults to
    ``size_mm / 3``; a finer one keeps more of the shape (a 14 mm model of the quick
    twin's reference scan: 0.62 mm sd from the scan on the default 4.7 mm grid, 0.24 mm
    on a 1 mm one, 0.15 mm without a remesh).
    """
    import open3d as o3d
    import trimesh
    from skimage.measure import marching_cubes

    h = size_mm / 3.0 if grid_mm is None else float(grid_mm)
    if not h > 0:
        raise ValueError(f"grid_mm must be > 0, got {grid_mm}")
    lo, hi = vertices.min(0) - 2 * h, vertices.max(0) + 2 * h
    axes = [np.arange(a, b + h, h) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    occ = scene.compute_occupancy(o3d.core.Tensor(grid.astype(np.float32)), nsamples=5).numpy()
    vol = occ.reshape([len(a) for a in axes]).astype(float)
    v, f, _, _ = marching_cubes(vol, 0.5, spacing=(h, h, h))
    m = trimesh.Trimesh(v + lo, f[:, ::-1], process=True)
    m = max(m.split(only_watertight=True), key=lambda s: s.volume)
    trimesh.smoothing.filter_taubin(m, iterations=10)
    target = int(4 * m.area / (np.sqrt(3) * size_mm**2))
    # Quadric decimation can fold the surface onto itself (a pushed-through sphere at
    # 4 mm: self-intersecting and open at the target, clean at 1.5x it); coarsen less
    # until it is clean, else keep the smoothed marching-cubes surface (clean by design).
    for factor in _DECIMATION_FACTORS:
        if len(m.faces) <= factor * target:
            break
        om = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.asarray(m.vertices)),
            o3d.utility.Vector3iVector(np.asarray(m.faces, dtype=np.int32)),
        )
        om = om.simplify_quadric_decimation(target_number_of_triangles=int(factor * target))
        d = trimesh.Trimesh(np.asarray(om.vertices), np.asarray(om.triangles), process=True)
        defects = surface_defects(d.vertices, d.faces)
        if not defects:
            m = d
            break
        log.info("decimation to %d faces left the surface %s", len(d.faces), ", ".join(defects))
    trimesh.repair.fix_normals(m)
    return np.asarray(m.vertices), np.asarray(m.faces)


#: Decimation targets tried in turn, as multiples of the size's face count.
_DECIMATION_FACTORS = (1.0, 1.5, 2.0, 4.0)


def surface_defects(vertices: np.ndarray, faces: np.ndarray) -> list[str]:
    """What makes a surface unfit for TetGen (self-intersections, holes, non-manifold)."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, float)),
        o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)),
    )
    checks = {
        "self-intersecting": m.is_self_intersecting(),
        "not edge-manifold": not m.is_edge_manifold(allow_boundary_edges=False),
        "not vertex-manifold": not m.is_vertex_manifold(),
        "not watertight": not m.is_watertight(),
    }
    return [name for name, bad in checks.items() if bad]


def tetrahedralize(
    vertices_mm: np.ndarray,
    faces: np.ndarray,
    *,
    max_volume_mm3: float | None = None,
    min_ratio: float = 1.5,
    min_dihedral_deg: float = 10.0,
    max_dihedral_deg: float | None = None,
    regions: list | tuple = (),
    repair: bool = True,
    size_mm: float = 5.0,
    keep_planes: list | tuple = (),
) -> TetMesh:
    """Quality tetrahedral mesh of a closed surface (TetGen).

    Parameters
    ----------
    vertices_mm : ndarray, shape (n, 3)
    faces : ndarray, shape (m, 3)
        A closed triangle surface; internal closed surfaces (inclusions) may be added.
    max_volume_mm3 : float, optional
        Upper bound of element volume.
    min_ratio : float
        Bound of the radius-edge ratio (TetGen ``-q``).
    min_dihedral_deg : float
        Bound of the smallest dihedral angle.
    max_dihedral_deg : float, optional
        The largest dihedral angle TetGen's mesh optimisation (flips and smoothing, its
        ``-o/`` switch) works to get every element below; None keeps the ``tetgen``
        package's own value (177 degrees). A sliver has dihedral angles near 0 and 180
        degrees, so a lower bound removes slivers: 165 degrees leaves 2.4-13 times fewer
        (median 5) elements with an angle below 5 or above 175 degrees on the quick twins'
        reference meshes (``benchmarks/bench_reference.py --max-dihedral``). It helps the
        straight stress-free recovery where a sliver stops it, not everywhere (README).
    regions : sequence of (tag, point_mm) or (tag, point_mm, max_volume_mm3)
        Region seeds: every element of the closed region containing the point gets the tag
        (and, with a third item, a volume of at most that, TetGen's ``-a`` without a
        number); elements of a region no seed lies in get ``bulk``.
    repair : bool
        When TetGen rejects the surface (self-intersections, holes), repair it and, if
        that fails, remesh it, then try again; logs what was done.
    size_mm : float
        Edge length used if the surface must be remeshed.
    keep_planes : sequence of (point_mm, normal, tol_mm)
        Planar parts of the surface (a support's back plane) to keep exactly flat: after
        a repair or a remesh (marching cubes and smoothing move them off the plane, so
        a support's node set found on the plane would come out empty), the vertices
        within ``tol_mm`` of each plane are projected back onto it.

    Returns
    -------
    TetMesh
        Positively oriented, with region tags (``bulk`` = 1 when no regions are given).
    """
    check_max_dihedral_deg(max_dihedral_deg)
    planes = [_plane(p) for p in keep_planes]

    def flat(v, f):
        return _onto_planes(v, planes), f

    attempts = [("as given", lambda v, f: (v, f))]
    if repair:
        attempts += [("repaired", lambda v, f: flat(*_repair_surface(v, f)))]
        attempts += [("remeshed", lambda v, f: flat(*remesh_surface(v, f, size_mm=size_mm)))]
    errors = []
    for label, fix in attempts:
        try:
            v, f = fix(np.asarray(vertices_mm, float), np.asarray(faces, np.int64))
            # TetGen may crash the process on a defective surface: give it clean ones only.
            # (Internal inclusion surfaces make the PLC non-manifold by design: not checked.)
            defects = [] if regions else surface_defects(v, f)
            if defects:
                raise ValueError("surface is " + ", ".join(defects))
            nodes, tets, region = _tetgen(
                v, f, max_volume_mm3, min_ratio, min_dihedral_deg, regions, max_dihedral_deg
            )
        except (RuntimeError, ValueError) as exc:
            errors.append(f"{label}: {exc}")
            continue
        if label != "as given":
            log.warning("TetGen rejected the surface; meshed it after it was %s", label)
        names = {k: v for k, v in REGION_IDS.items() if v in set(np.unique(region))}
        names = names or {"bulk": int(region[0])}
        return TetMesh(nodes, tets, region, names).oriented()
    raise MeshError("TetGen could not mesh the surface: " + "; ".join(errors))


def _plane(spec) -> tuple[np.ndarray, np.ndarray, float]:
    point, normal, tol = spec
    n = np.asarray(normal, float)
    if n.shape != (3,) or not np.linalg.norm(n) > 0 or not tol > 0:
        raise ValueError(f"keep_planes entries are (point_mm, normal, tol_mm > 0), got {spec!r}")
    return np.asarray(point, float).reshape(3), n / np.linalg.norm(n), float(tol)


def _onto_planes(vertices: np.ndarray, planes) -> np.ndarray:
    """Project the vertices within each plane's tolerance onto it."""
    v = np.array(vertices, float)
    for p0, n, tol in planes:
        d = (v - p0) @ n
        near = np.abs(d) < tol
        v[near] -= np.outer(d[near], n)
    return v


#: A flat face's tolerance relative to the body's largest extent (on top of
#: ``dist_tol_mm``): a cast base bowed 0.1 mm over 80 mm, or a segmented one rough to
#: 0.015 mm, is one face (review BU).
FLAT_REL_TOL = 2e-3
#: A runner-up flat face at least this share of the largest one's area: which is the back
#: cannot be told from the mesh (review BU: a box's base or its top, by element order).
FLAT_TIE_RATIO = 0.9
#: Near a flat face: boundary triangles facing its way within this angle (degrees), every
#: vertex within this many tolerances of its plane. A patch of the same face bowed beyond
#: the tolerance lies near it (no rival face; its nodes left free are warned of).
NEAR_ANGLE_DEG, NEAR_TOLERANCES = 10.0, 10.0


def _boundary_triangles(mesh: TetMesh):
    """Boundary triangles: nodes (k, 3), vertices (k, 3, 3) mm, unit normals, areas mm^2.

    The normals (k, 3) point outward for positive tets; the areas have shape (k,).
    """
    faces = boundary_faces(mesh.tets)
    x = mesh.nodes_mm[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area = np.linalg.norm(n, axis=1) / 2
    return faces, x, n / (2 * area[:, None]), area


def find_back_plane(mesh: TetMesh, *, angle_tol_deg: float = 2.0, dist_tol_mm: float = 0.05):
    """Nodes of the largest flat part of the boundary (the back face).

    Boundary triangles are grouped by the plane of a seed triangle (largest first), and
    each group is grown to the plane fitted to it until it stops changing, so that a face
    bowed or rough within the tolerance is found whole, not as the patch around the seed
    (review BU: a base bowed 0.1 mm over 80 mm was clamped on 71 of its 114 nodes).

    Parameters
    ----------
    mesh : TetMesh
    angle_tol_deg, dist_tol_mm : float
        Boundary triangles whose outward normals lie within the angle of the group's
        plane and whose vertices lie within ``max(dist_tol_mm, FLAT_REL_TOL x extent)``
        of it belong to it (extent: the body's largest bounding-box side, mm).

    Returns
    -------
    nodes : ndarray of int
    normal : ndarray, shape (3,)
        Outward unit normal.
    offset_mm : float
        Plane offset, ``normal . x = offset`` on the plane.

    Raises
    ------
    MeshError
        No flat part covers 5 % of the boundary, or two distinct flat parts have nearly
        the same area (:data:`FLAT_TIE_RATIO`; both named).
    """
    faces, x, n, area = _boundary_triangles(mesh)
    cos_tol = np.cos(np.radians(angle_tol_deg))
    tol = flat_tolerance_mm(mesh, dist_tol_mm)

    def members(normal, offset):
        return (n @ normal > cos_tol) & (np.abs(x @ normal - offset).max(axis=1) < tol)

    def grown(member):
        for _ in range(10):  # each pass refits the plane to the group and regroups
            normal, offset, _ = plane_fit(mesh.nodes_mm[np.unique(faces[member])])
            if n[member].mean(axis=0) @ normal < 0:
                normal, offset = -normal, -offset
            again = members(normal, offset)
            if np.array_equal(again, member) or not again.any():
                break
            member = again
        return member, normal, offset

    groups = []  # (area, member, normal, offset) of the candidate faces
    tried = np.zeros(len(faces), dtype=bool)
    for seed in np.argsort(-area):
        if tried[seed]:
            continue
        member = members(n[seed], n[seed] @ x[seed, 0])
        tried |= member
        if area[member].sum() >= 0.01 * area.sum():  # a seed's patch may grow to the face
            member, normal, offset = grown(member)
            tried |= member
            if area[member].sum() >= 0.05 * area.sum():
                groups.append((float(area[member].sum()), member, normal, offset))
    if not groups:
        raise MeshError("no flat back face found: no planar part covers 5 % of the boundary")
    groups.sort(key=lambda g: -g[0])
    best_area, best, normal, offset = groups[0]
    for other_area, _, other_normal, other_offset in groups[1:]:
        # a patch of the same face bowed beyond the tolerance is no rival (warned below)
        near = other_normal @ normal > np.cos(np.radians(NEAR_ANGLE_DEG))
        same = near and abs(other_offset - offset) < NEAR_TOLERANCES * tol
        if not same and other_area >= FLAT_TIE_RATIO * best_area:
            raise MeshError(
                "two flat faces of nearly the same area could each be the back face: "
                f"{_plane_text(normal, offset, best_area)} and "
                f"{_plane_text(other_normal, other_offset, other_area)}; give --back-plane "
                "z=MM, or a `set:back` point-data mask of the back face's nodes"
            )
    nodes = np.unique(faces[best])
    _warn_left_near_plane((faces, x, n), nodes, normal, offset, tol, "the detected back face")
    return nodes, normal, offset


def flat_tolerance_mm(mesh: TetMesh, dist_tol_mm: float = 0.05) -> float:
    """How far (mm) a node may lie off a flat face and belong to it.

    ``max(dist_tol_mm, FLAT_REL_TOL x extent)``, the body's largest bounding-box side.
    """
    return max(dist_tol_mm, FLAT_REL_TOL * float(np.ptp(mesh.nodes_mm, axis=0).max()))


def warn_left_near_plane(
    mesh: TetMesh, nodes: np.ndarray, normal: np.ndarray, offset: float, tol: float, what: str
) -> int:
    """Warn of boundary nodes left out of a held face that lie near its plane; their count.

    A face rougher or more bowed than ``tol`` is found in part: the boundary triangles
    near the plane (:data:`NEAR_ANGLE_DEG`, :data:`NEAR_TOLERANCES`) whose nodes are not
    held are counted (review BU: such a patch was clamped without a word, the rest of the
    face left free).
    """
    faces, x, n, _ = _boundary_triangles(mesh)
    return _warn_left_near_plane((faces, x, n), nodes, normal, offset, tol, what)


def _warn_left_near_plane(triangles, nodes, normal, offset, tol, what) -> int:
    """:func:`warn_left_near_plane` of the boundary ``(faces, vertices, unit normals)``."""
    faces, x, n = triangles
    near = (n @ normal > np.cos(np.radians(NEAR_ANGLE_DEG))) & (
        np.abs(x @ normal - offset).max(axis=1) < NEAR_TOLERANCES * tol
    )
    left = np.setdiff1d(np.unique(faces[near]), nodes)
    if len(left):
        log.warning(
            "%s (%d nodes, within %.3g mm of its plane) leaves %d boundary nodes free that "
            "lie within %.3g mm of that plane, facing the same way: if the back face is "
            "rougher or more bowed than that, give a `set:back` point-data mask of its "
            "nodes",
            what,
            len(nodes),
            tol,
            len(left),
            NEAR_TOLERANCES * tol,
        )
    return len(left)


def _plane_text(normal: np.ndarray, offset: float, area_mm2: float) -> str:
    """``normal (0, 0, -1), offset 0 mm, 4800 mm^2``."""
    return (
        f"normal ({', '.join(f'{v + 0.0:.3g}' for v in normal)}), offset {offset + 0.0:.4g} mm, "
        f"{area_mm2:.4g} mm^2"
    )


def tag_node_sets(
    mesh: TetMesh,
    back_nodes: np.ndarray,
    back_normal: np.ndarray,
    *,
    nipple_mm: np.ndarray | None = None,
) -> TetMesh:
    """Add node sets ``back``, ``surface`` (boundary without the back) and ``nipple``.

    ``nipple`` is the surface node nearest ``nipple_mm`` (a measured nipple, mm), else the
    apex: the surface node highest above the back. Under a lateral load a nipple tips
    over (1.6-1.8 mm from the apex on the digital twin), and a phantom's highest point
    need not be its nipple.

    Raises
    ------
    MeshError
        When ``back_nodes`` has fewer than 3 nodes or no boundary face (a support there
        would hold nothing).
    """
    bnodes = np.unique(boundary_faces(mesh.tets))
    back_nodes = np.asarray(back_nodes, dtype=np.int64)
    faces = boundary_faces(mesh.tets)
    inset = np.zeros(mesh.n_nodes, dtype=bool)
    inset[back_nodes] = True
    if len(back_nodes) < 3 or not inset[faces].all(axis=1).any():
        raise MeshError(
            f"the back node set has {len(back_nodes)} nodes and "
            f"{int(inset[faces].all(axis=1).sum())} boundary faces: the back plane is not on "
            "the mesh boundary (a repaired or remeshed surface moves it; pass keep_planes to "
            "tetrahedralize)"
        )
    surface = np.setdiff1d(bnodes, back_nodes)
    if nipple_mm is None:
        height = -(mesh.nodes_mm[surface] - mesh.nodes_mm[back_nodes].mean(0)) @ back_normal
        nipple = surface[[int(np.argmax(height))]]
    else:
        gap = np.linalg.norm(mesh.nodes_mm[surface] - np.asarray(nipple_mm, float), axis=1)
        nipple = surface[[int(np.argmin(gap))]]
    return mesh.with_node_sets(back=back_nodes, surface=surface, nipple=nipple)


SKIN_FRACTION_BINS = 20
_PARTIAL_SKIN_TAG = 300  # tags 301..319: bulk elements partly inside the skin band


def skin_fraction(region_name: str) -> float | None:
    """Volume fraction of skin of a region: 1 for ``skin``, ``f`` for ``skin:f``, else None."""
    if region_name == "skin":
        return 1.0
    if region_name.startswith("skin:"):
        return float(region_name.split(":", 1)[1])
    return None


def subtet_centroids(levels: int = 2) -> np.ndarray:
    """Barycentric centroids of the ``8**levels`` equal-volume tets of a red refinement.

    Parameters
    ----------
    levels : int
        Red refinements of the reference tetrahedron.

    Returns
    -------
    ndarray, shape (8**levels, 4)
        Barycentric coordinates: a volume fraction sampled in steps of ``8**-levels``.
    """
    tets = [np.eye(4)]
    for _ in range(levels):
        children = []
        for v in tets:
            m = {(i, j): (v[i] + v[j]) / 2 for i in range(4) for j in range(i + 1, 4)}
            children += [
                np.array([v[0], m[0, 1], m[0, 2], m[0, 3]]),
                np.array([m[0, 1], v[1], m[1, 2], m[1, 3]]),
                np.array([m[0, 2], m[1, 2], v[2], m[2, 3]]),
                np.array([m[0, 3], m[1, 3], m[2, 3], v[3]]),
            ]
            # the inner octahedron, split along its diagonal m02-m13 into 4 tets
            ring = [m[0, 1], m[1, 2], m[2, 3], m[0, 3]]
            for a, b in zip(ring, ring[1:] + ring[:1], strict=True):
                children.append(np.array([m[0, 2], m[1, 3], a, b]))
        tets = children
    return np.array([t.mean(axis=0) for t in tets])


def _band_fraction(mesh: TetMesh, thickness_mm: float, back_nodes) -> np.ndarray:
    """Fraction of each element's volume within ``thickness_mm`` of the outer surface."""
    import open3d as o3d

    faces = boundary_faces(mesh.tets)
    outer = faces[~np.isin(faces, back_nodes).all(axis=1)]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.nodes_mm.astype(np.float32)), o3d.core.Tensor(outer.astype(np.uint32))
    )
    bary = subtet_centroids()
    pts = np.einsum("pk,ekj->epj", bary, mesh.nodes_mm[mesh.tets]).reshape(-1, 3)
    dist = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    return (dist.reshape(mesh.n_tets, len(bary)) < thickness_mm).mean(axis=1)


def _skin_regions(mesh: TetMesh, thickness_mm: float, back_nodes) -> TetMesh:
    """Tag bulk elements by the volume fraction of them inside the skin band.

    Elements (nearly) wholly inside the band become ``skin``; elements partly inside
    become ``skin:f`` with the fraction ``f`` rounded to 1/20 (a law can then mix the
    two materials by volume, so the layer's stiffness times volume does not depend on
    the mesh); elements (nearly) outside stay ``bulk``. Fractions are sampled at the
    centroids of the 64 equal sub-tetrahedra of two red refinements.
    """
    frac = _band_fraction(mesh, thickness_mm, back_nodes)
    k = np.rint(frac * SKIN_FRACTION_BINS).astype(int)
    bulk = mesh.region == REGION_IDS["bulk"]
    region = mesh.region.copy()
    names = dict(mesh.region_names)
    full = bulk & (k == SKIN_FRACTION_BINS)
    region[full] = REGION_IDS["skin"]
    if full.any():
        names["skin"] = REGION_IDS["skin"]
    for kk in np.unique(k[bulk & (k > 0) & (k < SKIN_FRACTION_BINS)]):
        region[bulk & (k == kk)] = _PARTIAL_SKIN_TAG + kk
        names[f"skin:{kk / SKIN_FRACTION_BINS:.2f}"] = _PARTIAL_SKIN_TAG + kk
    return mesh.with_regions(region, names)


def append_spheres(vertices, faces, spheres) -> tuple[np.ndarray, np.ndarray]:
    """A surface with icospheres appended as further closed surfaces (internal facets).

    Parameters
    ----------
    vertices : ndarray, shape (n, 3)
    faces : ndarray, shape (m, 3)
    spheres : sequence of (centre_mm, radius_mm, subdivisions)

    Returns
    -------
    vertices, faces : ndarray
        The input first, then each sphere's (:func:`fem.geometry.sphere_surface`).
    """
    verts, tris, off = [np.asarray(vertices)], [np.asarray(faces)], len(vertices)
    for c, r, level in spheres:
        v, f = sphere_surface(c, r, subdivisions=level)
        verts.append(v)
        tris.append(f + off)
        off += len(v)
    return np.vstack(verts), np.vstack(tris)


def inclusion_spheres(phantom: Phantom) -> list[tuple[np.ndarray, float, int]]:
    """The phantom's inclusions as the spheres :func:`mesh_phantom` embeds.

    Parameters
    ----------
    phantom : Phantom

    Returns
    -------
    list of (centre_mm, radius_mm, subdivisions)
        One per inclusion, in the phantom's order: centre, shape (3,), LPS mm; radius in
        mm; the icosphere's subdivisions (1 below 6 mm diameter, else 2), as
        :func:`append_spheres` takes them.
    """
    pairs = zip(phantom.inclusion_centres_mm, phantom.inclusion_diameters_mm, strict=True)
    return [(np.asarray(c), float(d) / 2, 1 if d < 6 else 2) for c, d in pairs]


def _inclusion_plc(phantom: Phantom, vertices, faces):
    return append_spheres(vertices, faces, inclusion_spheres(phantom))


def mesh_phantom(
    phantom: Phantom,
    *,
    size_mm: float = 6.0,
    embed_inclusions: bool = False,
    skin_thickness_mm: float | None = None,
    min_ratio: float = 1.5,
) -> TetMesh:
    """Tetrahedral mesh of the phantom with region tags and node sets.

    Parameters
    ----------
    phantom : Phantom
        Its surface should be triangulated at about ``size_mm`` (``PhantomSpec.resolution_mm``).
    size_mm : float
        Target element edge length in mm.
    embed_inclusions : bool
        Mesh the inclusions as conforming regions; else tag elements whose centroid
        lies inside an inclusion (cheaper, staircase boundaries).
    skin_thickness_mm : float, optional
        Tag a skin band of this thickness (defaults to the phantom spec's): regions
        ``skin`` and ``skin:f`` for elements partly in the band (see :func:`skin_fraction`).
    min_ratio : float
        Bound of the elements' radius-edge ratio (TetGen ``-q``; see
        :func:`tetrahedralize`).

    Returns
    -------
    TetMesh
        Regions ``bulk``, ``inclusion`` (and ``skin``); node sets ``back``,
        ``surface`` and ``nipple``.
    """
    vol = size_mm**3 / (6 * np.sqrt(2))
    v, f = phantom.vertices_mm, phantom.faces
    regions: list = []
    if embed_inclusions and len(phantom.inclusion_centres_mm):
        v, f = _inclusion_plc(phantom, v, f)
        bulk_seed = _bulk_seed(phantom)
        regions = [(REGION_IDS["bulk"], bulk_seed)]
        regions += [(REGION_IDS["inclusion"], c) for c in phantom.inclusion_centres_mm]
    mesh = tetrahedralize(v, f, max_volume_mm3=vol, min_ratio=min_ratio, regions=regions)
    if not embed_inclusions:
        mesh = _tag_inclusions_by_centroid(mesh, phantom)
    back = np.flatnonzero(np.abs(mesh.nodes_mm[:, 2]) < 1e-6)
    mesh = tag_node_sets(mesh, back, np.array([0.0, 0.0, -1.0]))
    skin = phantom.spec.skin_thickness_mm if skin_thickness_mm is None else skin_thickness_mm
    return _skin_regions(mesh, skin, back) if skin > 0 else mesh


def _bulk_seed(phantom: Phantom) -> np.ndarray:
    """A point inside the body, away from every inclusion (just above the back plate)."""
    rng = np.random.default_rng(0)
    lo, hi = phantom.vertices_mm.min(0), phantom.vertices_mm.max(0)
    for _ in range(1000):
        p = np.array([*rng.uniform(lo[:2] * 0.3, hi[:2] * 0.3), rng.uniform(0.5, 2.0)])
        d = np.linalg.norm(phantom.inclusion_centres_mm - p, axis=1)
        if np.all(d > phantom.inclusion_diameters_mm / 2 + 0.5):
            return p
    raise MeshError("could not find a bulk seed point outside the inclusions")


def _tag_inclusions_by_centroid(mesh: TetMesh, phantom: Phantom) -> TetMesh:
    cent = mesh.nodes_mm[mesh.tets].mean(axis=1)
    region = mesh.region.copy()
    for c, d in zip(phantom.inclusion_centres_mm, phantom.inclusion_diameters_mm, strict=True):
        region[np.linalg.norm(cent - c, axis=1) < d / 2] = REGION_IDS["inclusion"]
    names = {"bulk": REGION_IDS["bulk"]}
    if np.any(region == REGION_IDS["inclusion"]):
        names["inclusion"] = REGION_IDS["inclusion"]
    return mesh.with_regions(region, names)
