"""The FE model of the reference scan: its surface meshed, the back plane tagged."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import Literal

import numpy as np

import fem
from fem.mesh import REGION_IDS
from fem.meshing import (
    append_spheres,
    remesh_surface,
    surface_defects,
    tag_node_sets,
    tetrahedralize,
)

from ..data.measurements import ScanMeasurement
from .residuals import surface_area_mm2

__all__ = [
    "MeshSupport",
    "meshed_spheres",
    "BODY_SCALE_HEIGHT_MM",
    "body_height_mm",
    "body_scale",
    "scale_of",
    "scan_height_mm",
    "model_mesh_notes",
    "plate_height_mm",
    "reference_mesh",
    "reference_mesh_with_support",
    "remesh_grids_mm",
]

log = logging.getLogger(__name__)


def _decimate(vertices: np.ndarray, faces: np.ndarray, size_mm: float):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces.astype(np.int32))
    )
    area = m.get_surface_area()
    target = max(200, int(4.0 * area / (np.sqrt(3.0) * size_mm**2)))
    if len(faces) > target:
        m = m.simplify_quadric_decimation(target_number_of_triangles=target)
    m.remove_degenerate_triangles()
    m.remove_unreferenced_vertices()
    return np.asarray(m.vertices), np.asarray(m.triangles)


#: The model's back face: boundary nodes within this distance of the back plane (mm), or
#: within the face's roughness where that is more (:func:`back_tolerance_mm`).
BACK_TOL_MM = 1.0


@dataclass(frozen=True)
class MeshSupport:
    """How a model mesh's back face was put on the back plane and clamped.

    Attributes
    ----------
    surface : {"decimated", "remeshed", "repaired"}
        The surface TetGen meshed: the scan's decimated; the scan's remeshed on a
        :data:`REMESH_GRID_MM` grid (the decimated rejected); or the decimated repaired or
        remeshed coarsely by :func:`fem.meshing.tetrahedralize` (both rejected).
    back_tol_mm : float
        How far off the back plane the surface's vertices were put onto it (and so
        clamped): :func:`back_tolerance_mm` on the decimated surface, at least ``size_mm
        / 5`` on the others.
    clamped_mm2, plate_mm2 : float, float or None
        The clamped area and the scan's back-plate area (:func:`support_mm2`).
    """

    surface: Literal["decimated", "remeshed", "repaired"]
    back_tol_mm: float
    clamped_mm2: float
    plate_mm2: float | None

    def as_dict(self) -> dict:
        """The record ``calibration.json`` keeps under ``mesh.support``."""
        return {
            "surface": self.surface,
            "back_tol_mm": self.back_tol_mm,
            "clamped_mm2": self.clamped_mm2,
            "plate_mm2": self.plate_mm2,
        }


def reference_mesh(ref: ScanMeasurement, **options):
    """Tetrahedral mesh of the reference scan's surface with node sets.

    :func:`reference_mesh_with_support` without the support's record; the same options.

    Returns
    -------
    TetMesh
    """
    return reference_mesh_with_support(ref, **options)[0]


def reference_mesh_with_support(
    ref: ScanMeasurement,
    *,
    size_mm: float = 8.0,
    back_tol_mm: float = BACK_TOL_MM,
    max_dihedral_deg: float | None = None,
    spheres: Sequence[tuple[Sequence[float], float]] = (),
    sphere_size_mm: float | None = None,
):
    """Tetrahedral mesh of the reference scan's surface with node sets, and its support.

    Boundary nodes within ``back_tol_mm`` of the measured back plane (or the back face's
    own roughness, :func:`back_tolerance_mm`) form the ``back`` set and are projected
    onto the plane, so the support is exactly flat. The surface is
    decimated to about the size's face count; when TetGen rejects that, the scan's full
    surface is remeshed on a fine grid (:func:`_remeshed`), and when it rejects that too,
    :func:`fem.meshing.tetrahedralize` repairs or remeshes the decimated one.

    Parameters
    ----------
    ref : ScanMeasurement
        The reference scan (reference frame, mm).
    size_mm : float
        Target element edge length.
    back_tol_mm : float
    max_dihedral_deg : float, optional
        TetGen's optimisation bound on the largest dihedral angle
        (:func:`fem.meshing.tetrahedralize`); None: the ``tetgen`` package's own.
    spheres : sequence of (centre_mm, diameter_mm)
        Spheres (the inclusions ingest segmented in the reference scan) meshed as internal
        surfaces, so that elements do not straddle them, with elements of
        ``sphere_size_mm`` inside (region ``inclusion``); the sphere's surface is an
        icosphere of edges nearest that size (one subdivision at least). Each must lie
        inside the body, clear of the surface and of the others by an eighth of an inner
        element (:data:`SPHERE_CLEARANCE`).
        Spheres narrower than ``sphere_size_mm`` are not meshed (a region tagging by
        volume fraction, :func:`calib.model.effects.tag_effect_regions`, still sees them).
    sphere_size_mm : float, optional
        Element edge length inside the spheres; default ``size_mm / 2``.

    Returns
    -------
    mesh : TetMesh
        Nodes in the reference frame (mm); node sets ``back``, ``surface``, ``nipple`` (the
        surface node nearest the scan's measured nipple).
    support : MeshSupport
        Which surface was meshed, how far off the plane its vertices were clamped, and the
        clamped and back-plate areas (a warning below :data:`SUPPORT_AREA_SHARE`).

    Raises
    ------
    fem.MeshError
        No usable surface (a field of view that cuts the body among them), or a sphere
        that reaches the surface or another sphere.
    """
    cut = getattr(ref, "fov_edge", None)
    if cut is not None and cut.any():
        raise fem.MeshError(
            f"reference scan {ref.name!r}: the field of view cuts the body ({int(cut.sum())} "
            "surface vertices on the volume's edge, flagged fov_edge by ingest): a model "
            "meshed from it would take the volume's edge for the phantom's surface; rescan "
            "the reference posture with the whole phantom in view, or make a scan that holds "
            "it the reference"
        )
    back_tol_mm = back_tolerance_mm(ref, back_tol_mm, size_mm)
    # a surface TetGen rejects is repaired or remeshed (fem.meshing.tetrahedralize); the
    # remeshed one comes from marching cubes on a size/3 grid, which leaves the back up to
    # half a grid step (size/6) off its plane: vertices that near it go back onto it, so
    # the support keeps its faces
    plane = (ref.back_point_mm, ref.back_normal, max(back_tol_mm, size_mm / 5.0))
    if spheres:
        h = size_mm / 2.0 if sphere_size_mm is None else sphere_size_mm
        mesh, surface, tol = _with_spheres(
            ref, size_mm, back_tol_mm, max_dihedral_deg, plane, spheres, h
        )
    else:
        mesh, surface, tol = _without_spheres(ref, size_mm, back_tol_mm, max_dihedral_deg, plane)
    return mesh, _support_checked(ref, mesh, surface, tol)


def _without_spheres(ref, size_mm, back_tol_mm, max_dihedral_deg, plane):
    """:func:`reference_mesh` without internal spheres, the surface's kind and tolerance.

    The decimated surface, its back within ``back_tol_mm`` put onto the plane; where
    TetGen rejects it, the scan's surface remeshed on a fine grid (:func:`_remeshed`), and
    where that fails too, :func:`fem.meshing.tetrahedralize`'s repair or coarse remesh of
    the decimated one, each with its back within ``plane``'s tolerance put onto it.
    """
    p0, n, _ = plane
    v, f = _decimate(ref.vertices_mm, ref.faces, size_mm)
    v, on = _onto_plane(v, (p0, n, back_tol_mm))
    if on < 3:
        raise fem.MeshError(
            f"reference scan {ref.name!r}: no surface vertices within {back_tol_mm:.2g} mm of the "
            "back plane; check the fiducials and the back-plate segmentation"
        )
    vol = size_mm**3 / (6.0 * np.sqrt(2.0))
    sizing = {"max_volume_mm3": vol, "size_mm": size_mm, "max_dihedral_deg": max_dihedral_deg}
    try:
        mesh, surface, tol = tetrahedralize(v, f, repair=False, **sizing), "decimated", back_tol_mm
    except fem.MeshError as exc:
        log.info("TetGen rejected the decimated reference surface (%s)", exc)
        mesh, tol = _remeshed(ref, plane, sizing, back_tol_mm)
        surface = "remeshed"
    if mesh is None:  # repaired, or remeshed on the coarse grid (fem.meshing says which)
        try:
            mesh = tetrahedralize(v, f, keep_planes=[plane], **sizing)
        except fem.MeshError as exc:  # which scan, which size: TetGen's words say neither
            raise fem.MeshError(
                f"reference scan {ref.name!r} at {size_mm:g} mm: its surface decimated to "
                f"{len(f)} faces was rejected, and remeshed on "
                f"{' and '.join(f'{g:g}' for g in remesh_grids_mm(ref))} mm grids "
                f"gave no mesh; {exc}"
            ) from exc
        surface, tol = "repaired", plane[2]
    mesh = _with_back(mesh, p0, n, size_mm, ref.nipple_mm)
    back = len(mesh.node_set("back"))
    log.info(
        "reference mesh: %d tets, %d nodes, %d on the back plane", mesh.n_tets, mesh.n_nodes, back
    )
    return mesh, surface, tol


#: Scan faces whose normal lies within this angle of the back plane's (degrees) make up
#: the flat back face whose roughness :func:`back_tolerance_mm` measures (the rim's wall,
#: also flagged over its lowest 1.5 mm, stands across it).
FACE_NORMAL_DEG = 30.0
#: The face's terraces reach this many times the median of those heights: terraces
#: spread evenly over T put the median at T / 2, and the decimated face's vertices sit at
#: their tops, some past them (5 mm slices, the plate 4 degrees off: median 0.76 mm,
#: tolerance 1.89 mm, 96 % of the base clamped, against 81 % at 1.25 times the 99th
#: percentile). The median, not a high percentile: the underside of a rim bulging past
#: the plate faces it too (the twins' 99th percentiles 0.5-1.7 mm, medians 0.09-0.21 mm).
FACE_MEDIAN_FACTOR = 2.5


def back_tolerance_mm(ref, back_tol_mm: float, size_mm: float) -> float:
    """How far off the back plane the model's back face may lie and still be clamped (mm).

    ``back_tol_mm``, or the scan's back face's own roughness where that is more:
    :data:`FACE_MEDIAN_FACTOR` times the median height above the plane of the vertices
    of faces that face the plate (outward normal within :data:`FACE_NORMAL_DEG` of the
    plane's; a flared wall faces away from it) and lie at most ``cap`` above it; the
    result at most ``cap``: half the slice thickness across the plate (what the scan cannot
    resolve of the face's height; ``ref.back_voxel_depth_mm``) and at most ``size_mm /
    5`` (the remeshed fallback's tolerance). Thick slices along a tilted plate terrace the
    face: 5 mm slices, the plate 4 degrees off them, spread it over 2 mm, and within 1 mm
    the model clamped 48 % of the base (review U). A base lifted off the plate by more than
    half a voxel stays unclamped (and warned about); the twins' faces give at most 0.53
    mm, so their tolerance stays ``back_tol_mm``; a scan without its voxel depth keeps it.
    """
    depth = getattr(ref, "back_voxel_depth_mm", None)
    if depth is None:
        return back_tol_mm
    cap = max(back_tol_mm, min(0.5 * float(depth), size_mm / 5.0))
    v, f, n = ref.vertices_mm, ref.faces, ref.back_normal  # n: out of the body
    h = (v - ref.back_point_mm) @ n * -1.0  # height above the plane, into the body
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.maximum(np.linalg.norm(normal, axis=1), 1e-300)
    facing = normal @ n > np.cos(np.radians(FACE_NORMAL_DEG)) * length
    low = np.zeros(len(v), bool)
    low[f[facing].ravel()] = True
    low &= (h >= 0.0) & (h <= cap)
    if not low.any():
        return back_tol_mm
    rough = FACE_MEDIAN_FACTOR * float(np.median(h[low]))
    return float(min(max(back_tol_mm, rough), cap))


#: Below this share of the scan's back-plate area (its triangles flagged ``back_plate``,
#: which take in the rim's lowest 1.5 mm) clamped by the model mesh, the support is
#: warned about. The quick twin's reference (seed 0, ``--effect none``): 0.96 on 12 and
#: 14 mm meshes.
SUPPORT_AREA_SHARE = 0.8


def support_mm2(ref, mesh) -> tuple[float, float | None]:
    """The model mesh's clamped area and the scan's back-plate area (mm^2).

    The clamped area: the boundary faces whose three nodes are in the ``back`` set; the
    plate's: the scan's faces whose three vertices are flagged ``back_plate`` (None where
    the scan has no flags).
    """
    faces = fem.boundary_faces(mesh.tets)[:, :3]
    on = np.zeros(mesh.n_nodes, bool)
    on[mesh.node_set("back")] = True
    clamped = surface_area_mm2(mesh.nodes_mm, faces[on[faces].all(axis=1)])
    flags = getattr(ref, "back_plate", None)
    if flags is None:
        return clamped, None
    plate = surface_area_mm2(
        ref.vertices_mm, ref.faces[np.asarray(flags, bool)[ref.faces].all(axis=1)]
    )
    return clamped, plate


def _support_checked(ref, mesh, surface: str, back_tol_mm: float) -> MeshSupport:
    """``mesh``'s support, with a warning where it clamps little of the scan's plate.

    Only the scan's vertices within ``back_tol_mm`` of the back plane are put on it and
    clamped; a back face rougher than that (thick slices, a tilted plate) or a plane off
    the face leaves part of it free, and the fit then reads the missing support as a
    softer material. Scans without back-plate flags are not checked.
    """
    clamped, plate = support_mm2(ref, mesh)
    if plate is not None and plate > 0 and clamped < SUPPORT_AREA_SHARE * plate:
        log.warning(
            "reference scan %r: the model mesh clamps %.0f mm^2 of the %.0f mm^2 flagged as "
            "back plate (%.0f %%): the back face lies more than %.2g mm off the back plane in "
            "places (a base lifted off the plate, or a plane off the face: ingest.json "
            "back_plane); the fit reads the missing support as a softer material",
            ref.name,
            clamped,
            plate,
            100.0 * clamped / plate,
            back_tol_mm,
        )
    return MeshSupport(surface, back_tol_mm, clamped, plate)


#: Farther than this (mm) from the measured nipple, the model's nipple node is said: its
#: residual then carries that offset. The twins' reference meshes: 0.75-1.56 mm (8.6 to
#: 19.6 mm meshes); a smooth dome without a nipple bump: 3.5-6.3 mm on 12 mm meshes.
NIPPLE_NODE_OFFSET_MM = 2.5
#: Fewer elements than this through the body's height (height / mesh size), the mesh is
#: said to be coarse for the body. The twins: 6.3 at 12 mm, 5.4 at 14 mm (75 mm tall).
MIN_ELEMENTS_IN_HEIGHT = 4.0
#: More elements than this through the body's height, the mesh is said to be fine for the
#: body (slow to solve): a body twice the twins' size gets 12.6 elements of the default 12
#: mm, 30,089 tetrahedra and 81 s per FE solve against the twins' 4 s.
MAX_ELEMENTS_IN_HEIGHT = 12.0


#: The body height (above the back plate, mm) the lengths of the noise models and the
#: diagnosis' regions are sized for: the twins' (heights 71.3-78.7 mm, 74.5 mm typical).
BODY_SCALE_HEIGHT_MM = 75.0


def body_scale(body_height_mm: float) -> float:
    """Factor on the lengths sized for a twin-tall body, for a body of this height.

    The noise models' variogram reach (calibrate's and the diagnosis') and the
    diagnosis' region radii are sized for a body :data:`BODY_SCALE_HEIGHT_MM` tall and
    scale with the body's height: on a body half as tall an unscaled 40 mm reach spans
    most of it, and fits its smooth misfit as correlated noise (review BN, N4).

    Parameters
    ----------
    body_height_mm : float
        The body's greatest height above the back plate (mm).

    Returns
    -------
    float
        ``body_height_mm / BODY_SCALE_HEIGHT_MM`` rounded to one decimal (at least 0.1):
        1 for every twin, so their lengths are as before.

    Raises
    ------
    ValueError
        ``body_height_mm`` not a positive finite number.
    """
    if not (np.isfinite(body_height_mm) and body_height_mm > 0):
        raise ValueError(f"body height must be positive, got {body_height_mm!r} mm")
    return max(0.1, round(float(body_height_mm) / BODY_SCALE_HEIGHT_MM, 1))


def scan_height_mm(ref) -> float:
    """The reference scan's surface height above its back plane, mm (0 without vertices).

    The height :func:`body_scale` is taken of, everywhere (calibrate's noise model, the
    remesh grid, the diagnosis): the scan's own, not a model mesh's, which can stand about
    a millimetre taller (review BQ: 75.31 against 74.51 mm on the quick twin).

    Parameters
    ----------
    ref : ScanMeasurement
        The reference scan (``vertices_mm``, ``back_point_mm``, ``back_normal``).

    Returns
    -------
    float
    """
    v = np.asarray(ref.vertices_mm, float)
    return float(plate_height_mm(ref, v).max()) if len(v) else 0.0


def plate_height_mm(scan, points_mm: np.ndarray) -> np.ndarray:
    """Distance of points (reference frame, mm) from a scan's back plate, shape (n,)."""
    return np.abs((points_mm - scan.back_point_mm) @ scan.back_normal)


def scale_of(ref) -> float:
    """:func:`body_scale` of the reference scan's :func:`scan_height_mm` (1 where none).

    Parameters
    ----------
    ref : ScanMeasurement

    Returns
    -------
    float
    """
    height = scan_height_mm(ref)
    return body_scale(height) if np.isfinite(height) and height > 0 else 1.0


def body_height_mm(ref, mesh) -> float:
    """The model mesh's height above the reference scan's back plane, mm.

    Parameters
    ----------
    ref : ScanMeasurement
        The reference scan (its ``back_point_mm`` and ``back_normal``, into the body).
    mesh : fem.TetMesh
        Its model mesh.

    Returns
    -------
    float
    """
    return float(np.max((ref.back_point_mm - mesh.nodes_mm) @ ref.back_normal))


def model_mesh_notes(ref, mesh, size_mm: float, *, asked: bool = False) -> list[str]:
    """What a user should know about a calibration's model mesh of ``ref`` (may be empty).

    The model's nipple is the surface node nearest the measured nipple: on a coarse mesh
    of a smooth dome it can lie several mm away (:data:`NIPPLE_NODE_OFFSET_MM`). A body
    only a few elements tall (:data:`MIN_ELEMENTS_IN_HEIGHT`) is meshed far more coarsely
    than the twins the README's figures come from; one many elements tall
    (:data:`MAX_ELEMENTS_IN_HEIGHT`) far more finely, and solves far more slowly: said
    only of a size the user did not ask for (the default's).

    Parameters
    ----------
    ref : ScanMeasurement
        The reference scan.
    mesh : fem.TetMesh
        Its model mesh (:func:`reference_mesh`).
    size_mm : float
        The mesh size asked for.
    asked : bool
        Whether the user chose ``size_mm`` (``--mesh-size``): a fine mesh is then meant.

    Returns
    -------
    list of str
    """
    notes = []
    k = int(mesh.node_set("nipple")[0])
    offset = float(np.linalg.norm(mesh.nodes_mm[k] - ref.nipple_mm))
    if offset > NIPPLE_NODE_OFFSET_MM:
        notes.append(
            f"the model's nipple node lies {offset:.1f} mm from the measured nipple (the "
            f"{size_mm:g} mm mesh's nearest surface node): nipple errors carry that offset; "
            "a smaller --mesh-size brings a node nearer"
        )
    height = body_height_mm(ref, mesh)
    if height < MIN_ELEMENTS_IN_HEIGHT * size_mm:
        notes.append(
            f"the body is {height:.0f} mm tall: {height / size_mm:.1f} elements of "
            f"{size_mm:g} mm through its height, fewer than {MIN_ELEMENTS_IN_HEIGHT:g}; "
            f"consider --mesh-size {height / 6:.0f}"
        )
    elif height > MAX_ELEMENTS_IN_HEIGHT * size_mm and not asked:
        notes.append(
            f"the body is {height:.0f} mm tall: {height / size_mm:.1f} elements of "
            f"{size_mm:g} mm through its height ({mesh.n_tets} tetrahedra), more than "
            f"{MAX_ELEMENTS_IN_HEIGHT:g}: each FE solve is slow (the twins have about 6); "
            f"--mesh-size {height / 6:.0f} is about as fine as theirs"
        )
    return notes


def _with_back(mesh, p0, n, size_mm: float, nipple_mm: np.ndarray):
    """The mesh with its node sets (:func:`fem.meshing.tag_node_sets`).

    ``back``: the boundary nodes on the plane ``(p0, n)``; ``nipple``: the surface node
    nearest the measured ``nipple_mm``.
    """
    bnodes = np.unique(fem.boundary_faces(mesh.tets))
    back = bnodes[np.abs((mesh.nodes_mm[bnodes] - p0) @ n) < 1e-6 * size_mm]
    return tag_node_sets(mesh, back, n, nipple_mm=nipple_mm)


#: Smallest gap between a meshed sphere and the outer surface or another sphere, in inner
#: elements: TetGen fills a narrow gap with small elements, and an intersection may crash
#: it. Half an element refused the quick twins' inclusions x5 on seeds 0 and 1 (an 8.3 mm
#: inclusion 3.9 mm under the surface, with 8 mm elements).
SPHERE_CLEARANCE = 0.125

#: Mean edge of an icosphere of radius 1 after 0, 1, 2, 3 subdivisions (trimesh). One at
#: least: the icosahedron holds 61 % of its sphere's volume, one subdivision 87 %.
_ICO_EDGE = np.array([1.0515, 0.5823, 0.2993, 0.1508])


def meshed_spheres(spheres, sphere_size_mm: float) -> list:
    """The spheres :func:`reference_mesh` meshes: those at least ``sphere_size_mm`` wide.

    Narrower ones are left to the volume-fraction tagging
    (:func:`calib.model.effects.tag_effect_regions`): meshing them would force elements
    smaller than the size asked for.
    """
    return [(c, d) for c, d in spheres if float(d) >= sphere_size_mm]


def _sphere_plc(spheres, outer_v, outer_f, h: float):
    """The outer surface with the spheres appended as internal surfaces, and their seeds.

    Spheres narrower than ``h`` are left out. Raises ``fem.MeshError`` for a sphere
    within ``SPHERE_CLEARANCE * h`` of the outer surface or of another sphere (TetGen may
    crash the process on intersecting surfaces).
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(outer_v.astype(np.float32)), o3d.core.Tensor(outer_f.astype(np.uint32))
    )
    diameters = np.array([float(d) for _, d in spheres])
    if not np.all(diameters > 0):
        raise fem.MeshError(f"sphere diameters must be positive, got {diameters}")
    kept = meshed_spheres(spheres, h)
    if not kept:
        return outer_v, outer_f, []
    centres = np.array([np.asarray(c, float).reshape(3) for c, _ in kept])
    radii = np.array([0.5 * float(d) for _, d in kept])
    # open3d's signed distance is negative inside a closed surface
    depth = -scene.compute_signed_distance(o3d.core.Tensor(centres.astype(np.float32))).numpy()
    surfaces, regions = [], []
    for i, (c, r) in enumerate(zip(centres, radii, strict=True)):
        if depth[i] < r + SPHERE_CLEARANCE * h:
            raise fem.MeshError(
                f"inclusion at {np.round(c, 1).tolist()} mm (diameter {2 * r:.1f} mm) lies "
                f"{depth[i]:.1f} mm inside the reference surface: it reaches within "
                f"{SPHERE_CLEARANCE * h:g} mm of it, so it cannot be meshed as an internal sphere"
            )
        gap = np.linalg.norm(centres - c, axis=1) - radii - r
        gap[i] = np.inf
        if gap.min() < SPHERE_CLEARANCE * h:
            j = int(np.argmin(gap))
            where = [np.round(x, 1).tolist() for x in (c, centres[j])]
            raise fem.MeshError(
                f"inclusions at {where[0]} and {where[1]} mm lie {gap[j]:.1f} mm apart (< "
                f"{SPHERE_CLEARANCE * h:g} mm): they cannot be meshed as two spheres"
            )
        level = 1 + int(np.argmin(np.abs(np.log(_ICO_EDGE[1:] * r / h))))  # edge nearest h
        surfaces.append((c, r, level))
        regions.append((REGION_IDS["inclusion"], c, h**3 / (6.0 * np.sqrt(2.0))))
    return *append_spheres(outer_v, outer_f, surfaces), regions


def _with_spheres(ref, size_mm, back_tol_mm, max_dihedral_deg, plane, spheres, h):
    """:func:`reference_mesh` with internal spheres, the outer surface's kind and tolerance.

    The outer surface is tried as the plain mesh tries it (decimated, then the scan's
    surface remeshed on a fine grid), with the spheres inside; TetGen's repair fallbacks
    do not apply to a surface with inner ones.
    """
    if not 0 < h <= size_mm:
        raise fem.MeshError(f"sphere element size must lie in (0, {size_mm:g}] mm, got {h}")
    p0, n, _ = plane

    def decimated():
        v, f = _decimate(ref.vertices_mm, ref.faces, size_mm)
        return _onto_plane(v, (p0, n, back_tol_mm))[0], f, back_tol_mm

    def remeshed(grid_mm: float):
        return _remeshed_onto_plane(ref, plane, size_mm, back_tol_mm, grid_mm)[:3]

    vol = size_mm**3 / (6.0 * np.sqrt(2.0))
    errors = []
    outers = (
        ("decimated", decimated),
        *(("remeshed", partial(remeshed, grid)) for grid in remesh_grids_mm(ref)),
    )
    for label, outer in outers:
        try:
            w, g, tol = outer()
        except ValueError as exc:  # remesh_surface on a surface it cannot grid
            errors.append(f"{label}: {exc}")
            continue
        defects = surface_defects(w, g)
        if defects:  # TetGen may crash the process on a defective surface
            errors.append(f"{label}: surface is {', '.join(defects)}")
            continue
        pv, pf, regions = _sphere_plc(spheres, w, g, h)  # a sphere that does not fit: raised
        try:
            mesh = tetrahedralize(
                pv,
                pf,
                max_volume_mm3=vol,
                regions=regions,
                repair=False,
                size_mm=size_mm,
                max_dihedral_deg=max_dihedral_deg,
            )
        except fem.MeshError as exc:
            errors.append(f"{label}: {exc}")
            continue
        log.info(
            "reference mesh (%s surface) with %d inclusion spheres of %g mm elements: "
            "%d tets, %d nodes",
            label,
            len(meshed_spheres(spheres, h)),
            h,
            mesh.n_tets,
            mesh.n_nodes,
        )
        return _with_back(mesh, p0, n, size_mm, ref.nipple_mm), label, tol
    raise fem.MeshError(
        "TetGen could not mesh the reference surface with its inclusions: " + "; ".join(errors)
    )


#: Grid step (mm) of the remesh of a reference surface whose decimation TetGen rejects.
REMESH_GRID_MM = 1.0
#: A second grid step (mm), tried where the first grid's remesh is rejected too: its back
#: put onto the plane can fold at the rim on one grid and not on another (an independent
#: generator's dome, seed 3, its back put onto the plane within the former size/5: rejected
#: on 1 mm, meshed on 0.7, 1.3, 1.6 and 2 mm; the decimation's repair that followed left
#: 0.45-0.54 mm surface errors against 0.14-0.22 on its other seeds).
REMESH_GRID_RETRY_MM = 1.3


def remesh_grids_mm(ref: ScanMeasurement) -> tuple[float, float]:
    """The remesh's grid steps for this reference scan's body (mm).

    :data:`REMESH_GRID_MM` and :data:`REMESH_GRID_RETRY_MM` on a body no taller than the
    twins; on a taller one both times :func:`body_scale` of its height above the back
    plane, so the grid holds as many steps across it as across a twin: the occupancy grid
    grows with the cube of the body's size (a body twice the twins' on a 1 mm grid: about
    12 million points, minutes and a gigabyte; review BN, N6). A smaller body keeps the
    twins' steps, finer for its size (the grid's cost falls with it).

    Parameters
    ----------
    ref : ScanMeasurement
        The reference scan (``vertices_mm``, ``back_point_mm``, ``back_normal``).

    Returns
    -------
    tuple of float
        The first and the retry grid step, mm.
    """
    k = max(1.0, scale_of(ref))
    return REMESH_GRID_MM * k, REMESH_GRID_RETRY_MM * k


def _onto_plane(v: np.ndarray, plane) -> tuple[np.ndarray, int]:
    """The vertices within ``tol`` of the plane ``(p0, n, tol)`` put onto it (a copy).

    Returns the new vertices and how many were put onto the plane.
    """
    p0, n, tol = plane
    d = (v - p0) @ n
    near = np.abs(d) < tol
    return v - np.outer(np.where(near, d, 0.0), n), int(near.sum())


def remesh_tolerance_mm(back_tol_mm: float, grid_mm: float) -> float:
    """How far off the back plane a surface remeshed on ``grid_mm`` is put onto it (mm).

    The scan's back face lies within ``back_tol_mm`` of the plane (its measured
    roughness, :func:`back_tolerance_mm`), and marching cubes moves it by up to half a
    grid step: one grid step covers that with a factor of 2. It was ``size_mm / 5`` (the
    coarse size/3 grid's half step, with margin), 2.4 mm at 12 mm: on the independent
    generator's dome of seed 3 (a 6 mm wall) that clamped the rim's wall up to 2.4 mm
    above the plate, 7,400 of its 7,599 mm2 plate, and c1 came out at 410.6 Pa (95 %
    403.1-418.2; truth 420); with one grid step (1.3 mm) 7,229 mm2 and 415.3 Pa
    (405.3-425.6); its seeds whose decimation meshes clamp 7,291 mm2 at 1 mm.

    Parameters
    ----------
    back_tol_mm : float
        The back face's own tolerance (mm).
    grid_mm : float
        The remesh's grid step (mm).

    Returns
    -------
    float
    """
    return max(float(back_tol_mm), float(grid_mm))


def _remeshed_onto_plane(
    ref: ScanMeasurement, plane, size_mm: float, back_tol_mm: float, grid_mm: float
):
    """The scan's full surface remeshed on ``grid_mm``, its back put onto the plane.

    Returns the vertices, the faces, the tolerance within which vertices were put onto the
    plane (:func:`remesh_tolerance_mm`) and how many were.
    """
    w, g = remesh_surface(ref.vertices_mm, ref.faces, size_mm=size_mm, grid_mm=grid_mm)
    tol = remesh_tolerance_mm(back_tol_mm, grid_mm)
    w, on = _onto_plane(w, (plane[0], plane[1], tol))
    return w, g, tol, on


def _remeshed(ref: ScanMeasurement, plane, sizing: dict, back_tol_mm: float):
    """The scan's full surface remeshed on a fine grid, decimated, its back put on the plane.

    With 3 mm slices along the plate's normal (tilted 4 degrees: terraces), the quick
    twin's reference decimated self-intersecting at every target up to 4 times the count.
    :func:`fem.meshing.tetrahedralize`'s fallback remeshes that folded decimation on a
    size/3 grid (4.7 mm at 14 mm): 0.62 mm sd from the scan more than 3 mm from the plate,
    and c1 439.5 Pa (95 % 420.6-459.4; truth 420). The full surface on a
    :data:`REMESH_GRID_MM` grid (where that is rejected too, on
    :data:`REMESH_GRID_RETRY_MM`): 0.32 mm and 429.5 Pa (418.5-440.8); a scan that
    decimates cleanly: 0.15 mm. Its vertices within :func:`remesh_tolerance_mm` of the
    plane go onto it (within 1 mm only, before the back face's tolerance was measured,
    half the twin's terraced face was left unclamped, 3,587 against 7,331 mm2, and c1
    came out at 540 Pa).

    Returns
    -------
    mesh, tol_mm
        The mesh and the tolerance its back was put onto the plane with; ``(None, None)``
        when TetGen rejects it too.
    """
    for grid_mm in remesh_grids_mm(ref):
        try:
            w, g, tol, on = _remeshed_onto_plane(
                ref, plane, sizing["size_mm"], back_tol_mm, grid_mm
            )
            if on < 3:
                return None, None
            mesh = tetrahedralize(w, g, repair=False, **sizing)
        except (fem.MeshError, ValueError) as exc:
            log.info(
                "the reference surface remeshed on a %g mm grid was rejected too (%s)",
                grid_mm,
                exc,
            )
            continue
        log.warning(
            "TetGen rejected the decimated reference surface; meshed it after the scan's "
            "surface was remeshed on a %g mm grid (%d faces)",
            grid_mm,
            len(g),
        )
        return mesh, tol
    return None, None
