"""Landmarks: the back-plate plane, the nipple and the tracked tumour."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from imaging.errors import SegmentationError

__all__ = [
    "BackPlane",
    "Nipple",
    "estimate_back_plane",
    "find_nipple",
    "select_tumour",
    "voxel_depth_mm",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class BackPlane:
    """Back-plate plane.

    ``point_lps_mm`` (3,) on the body's flat back face, unit ``normal``
    (3,) pointing from the plate into the body, ``method`` ("fiducials" or "ransac") and
    ``beyond_face``: surface vertices more than ``face_tol_mm`` past the flat face (tissue
    that bulges past the plate's edge), left out of the face's height;
    ``fiducials_off_face_deg``: with fiducials, the angle between their plane and the
    surface's largest plane (the flat back face), or None where none was checked;
    ``voxel_depth_mm``: the scan's slice thickness across the plate
    (:func:`voxel_depth_mm`; None where the volume is not known).

    Attributes
    ----------
    point_lps_mm : numpy.ndarray, shape (3,)
        A point of the plane on the body's flat back face, scan LPS, mm (the markers' or
        the face band's centroid moved along the normal to the 1st percentile of the
        surface vertices' heights).
    normal : numpy.ndarray, shape (3,)
        Unit normal, scan LPS, pointing from the plate into the body.
    method : {"fiducials", "ransac"}
        Whether the normal is the fiducials' plane's or the surface's largest plane's.
    beyond_face : int
        Surface vertices more than ``face_tol_mm`` past the flat back face, left out of
        the plane's height.
    fiducials_off_face_deg : float or None
        Angle between the fiducials' plane and the surface's largest plane, degrees;
        None where no (non-collinear) fiducials were given.
    voxel_depth_mm : float or None
        The scan's slice thickness across the plate, mm; None without the scan's voxel
        matrix.
    """

    point_lps_mm: np.ndarray
    normal: np.ndarray
    method: str
    beyond_face: int = 0
    fiducials_off_face_deg: float | None = None
    voxel_depth_mm: float | None = None


@dataclass(frozen=True, eq=False)
class Nipple:
    """Nipple estimate.

    ``position_lps_mm`` (3,), ``height_mm`` above the back plane,
    ``quality`` (``refined``, ``fit_rms_mm``, ``n_cap_vertices``, ``shift_from_apex_mm``).

    Attributes
    ----------
    position_lps_mm : numpy.ndarray, shape (3,)
        The nipple, scan LPS, mm.
    height_mm : float
        Its height above the back plane (along the plane's normal), mm.
    quality : dict
        ``method`` (``"protrusion"``, ``"far protrusion"`` or ``"apex"``),
        ``protrusion_mm``, the quadratic fit's ``refined``, ``fit_rms_mm`` (mm),
        ``n_cap_vertices`` and (where it was fitted) ``fall_mm``, ``cap_radius_mm`` (apex
        only) and ``shift_from_apex_mm`` (from the highest vertex, mm); see
        :func:`find_nipple`.
    """

    position_lps_mm: np.ndarray
    height_mm: float
    quality: dict = field(default_factory=dict)


#: Histogram of the heights that finds the flat back face: bin width and the window
#: above the lowest vertex (mm), and how much denser than the window's median bin the
#: face's bin must be (a 50 mm disc puts ~100 times a wall's vertices in one 0.25 mm bin).
FACE_BIN_MM, FACE_WINDOW_MM, FACE_CONTRAST = 0.25, 10.0, 10.0

#: The fiducials' plane is trusted as the plate's while it lies within this angle of the
#: surface's largest plane (degrees). On the quick twin's four scans and the oblique test
#: scan the two agree to 0.01-0.07 degrees; markers not on the plate (posts, a tilted
#: frame) tilt the fiducials' plane, and the face's height then finds no face.
FIDUCIALS_OFF_FACE_DEG = 3.0
#: ... and while the face, tilted by that angle, rises less than this across its width
#: (mm) over the fiducials' plane: half the back-plate flag's 1.5 mm. An 80 mm face 2
#: degrees off rose 2.7 mm, and 44 % of it was left unflagged, scored as measured surface;
#: the twins' faces (0.01-0.07 degrees) rise at most 0.15 mm.
FACE_RISE_MM = 0.75
#: ... and while that largest plane holds at least this share of the surface's vertices
#: (the quick twin's back face: 16-21 %); a smaller one may not be the face.
FACE_MIN_SHARE = 0.05
#: ... or while the fiducials' plane, moved onto the face, holds this share of the
#: vertices the face's own plane holds in its band: a plane RANSAC found on a face thinned
#: by decimation (0.4-0.7 degrees off on one seed in ten, review U) fits the face no better
#: than the markers' plane. Markers tilted off a flat 80 mm face: 1.0 at 0.6 degrees (the
#: band holds the 0.8 mm rise), 0.90 at 0.8, 0.72 at 1.0, 0.38 at 2 degrees: kept up to
#: about 0.8 degrees (a 1.1 mm rise, within the back-plate flag's 1.5 mm).
FIDUCIALS_BAND_SHARE = 0.9
#: Half-thickness of the largest plane's band (mm): RANSAC's inlier distance, and the band
#: its least-squares refinement re-selects.
PLANE_BAND_MM = 0.5
#: Most refinements of the largest plane (each: the least-squares plane of the points in
#: its band, then the band again); on the twins' faces the band stops changing in 2-4.
PLANE_REFINEMENTS = 10


def _refined(v: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The least-squares plane of the points in a plane's band, re-selected until it holds.

    RANSAC's plane passes through three of the points and takes any tilt whose band of
    :data:`PLANE_BAND_MM` holds the most: on a face whose vertices scatter across the band
    (a voxel staircase, noise) tilts up to 2 x 0.5 mm across its width do alike (the quick
    twin's face, poisson seed 1: RANSAC's band 127 mm wide, 0.41 degrees off the truth,
    0.9 mm across it, and the fiducials' plane set aside for it). The total least-squares
    plane of the band (PCA) and the band about it, again, settle within 0.03 degrees of
    the truth on that twin's four scans from six RANSAC seeds
    (``tests/imaging/test_imaging_surface.py`` has a face of that kind).

    Returns
    -------
    normal : ndarray, shape (3,)
    origin : ndarray, shape (3,)
        The band's centroid.
    inside : ndarray of bool, shape (n,)
        The points within the band.
    """
    for _ in range(PLANE_REFINEMENTS):
        p = v[inside]
        origin = p.mean(axis=0)
        normal = np.linalg.svd(p - origin, full_matrices=False)[2][2]
        again = np.abs((v - origin) @ normal) <= PLANE_BAND_MM
        if np.array_equal(again, inside):
            break
        inside = again
    return normal, origin, inside


def _largest_plane(v: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The surface's largest plane: normal, point, inlier share and width.

    RANSAC's largest plane of points ``v`` (``PLANE_BAND_MM``), refined by least squares
    on its band (:func:`_refined`). The width is twice the 95th percentile of the
    inliers' distances from their centre (mm): a few wall or lip points within the
    plane's band do not widen it.
    """
    import open3d as o3d

    o3d.utility.random.seed(seed)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(v))
    _, inliers = pc.segment_plane(PLANE_BAND_MM, 3, 1000)  # its 3 points at least
    inside = np.zeros(len(v), bool)
    inside[np.asarray(inliers, dtype=int)] = True
    normal, origin, inside = _refined(v, inside)
    p = v[inside]
    r = np.linalg.norm(p - p.mean(axis=0), axis=1)
    width = 2.0 * float(np.percentile(r, 95.0))
    return normal, origin, float(inside.mean()), width


def voxel_depth_mm(voxel_mm: np.ndarray, normal: np.ndarray) -> float:
    """A scan's slice thickness across a plane: the longest voxel edge along its normal.

    ``voxel_mm`` (3, 3): the index-to-LPS matrix (columns: one voxel step along i, j, k,
    mm). ``max_i |a_i . n|``: 5 mm slices along the normal give about 5 mm; isotropic
    1.5 mm voxels at most 1.5 mm at any tilt (the box's projected diagonal, the sum, would
    give 2.4-2.5 mm on the twin's tilted scans, review V).
    """
    a = np.asarray(voxel_mm, float)
    return float(np.abs(a.T @ np.asarray(normal, float)).max())


def _band_share(v: np.ndarray, normal, face_normal, face_origin) -> float:
    """Share of ``v`` within the band of the plane of ``normal`` through the face's band.

    The face: the points within :data:`PLANE_BAND_MM` of the plane ``(face_origin,
    face_normal)``; the plane of ``normal`` passes through their median height along it.
    """
    face = np.abs((v - face_origin) @ face_normal) <= PLANE_BAND_MM
    h = v @ normal
    centre = float(np.median(h[face]))
    return float((np.abs(h - centre) <= PLANE_BAND_MM).mean())


def _face_height(h: np.ndarray, plane_h: float | None = None) -> float | None:
    """Height of the densest thin slab near the bottom (the flat back face), or None.

    The slab is searched within :data:`FACE_WINDOW_MM` above the lowest vertex, and up to
    half that window above ``plane_h`` (the height of the surface's largest plane, where it
    is parallel to the plate and in the body's lower half): tissue can hang further than
    the window past the plate's edge (a 12 mm lip put the plane 8.1 mm below the face of a
    120 x 80 mm dome, 12.0 mm below that of an 80 x 60 mm one).
    """
    lo = float(h.min())
    hi = lo + FACE_WINDOW_MM
    if plane_h is not None and plane_h - lo < 0.5 * (float(h.max()) - lo):
        hi = max(hi, plane_h + 0.5 * FACE_WINDOW_MM)
    counts, edges = np.histogram(h, np.arange(lo, hi + FACE_BIN_MM, FACE_BIN_MM))
    k = int(np.argmax(counts))
    if counts[k] < FACE_CONTRAST * max(float(np.median(counts)), 1.0):
        return None  # no flat face stands out (an open or face-less surface)
    return 0.5 * float(edges[k] + edges[k + 1])


def estimate_back_plane(
    vertices_lps_mm: np.ndarray,
    *,
    fiducials_lps_mm: np.ndarray | None = None,
    seed: int = 0,
    face_tol_mm: float = 1.0,
    voxel_mm: np.ndarray | None = None,
) -> BackPlane:
    """Estimate the back-plate plane of a body surface.

    With three or more non-collinear fiducials (which sit on the plate) the normal is the
    normal of their best-fit plane; otherwise it is the largest plane found by RANSAC on the
    surface vertices (the flat back face). Where that largest plane holds at least
    :data:`FACE_MIN_SHARE` of the vertices and the fiducials' plane lies more than
    :data:`FIDUCIALS_OFF_FACE_DEG` off it, or tilted enough that the face rises more than
    :data:`FACE_RISE_MM` over it (markers not on the plate), the face's plane is taken,
    with a warning; ``voxel_mm`` (3, 3), the scan's index-to-LPS matrix, raises that
    rise's bar to half the slice thickness across the face (:func:`voxel_depth_mm`: thick
    slices) and gives the plane's ``voxel_depth_mm``, and the markers' plane is kept where,
    moved onto the face, it holds :data:`FIDUCIALS_BAND_SHARE` times the vertices of the
    face's band. The normal is oriented towards the body (the side
    whose low end is a flat face, where only one end is; else the side holding most
    vertices, seen from the markers' plane) and the
    plane is moved onto the body's back face: the 1st percentile of the vertex heights,
    leaving out the vertices more than ``face_tol_mm`` below the densest 0.25 mm slab of
    heights near the bottom (the face; searched within 10 mm of the lowest vertex and,
    where the surface's largest plane is parallel to the plate, up to 5 mm above that
    plane's height under the body: :func:`_face_height`). A soft body in a lateral
    posture can bulge past the plate's edge, below the face (2.9-3.9 mm on a 200 Pa quick
    twin's lateral scans); counted in, those vertices moved the plane 1.7-2.1 mm off the
    face, left most of the face unflagged and the model mesh without a support.
    """
    v = np.asarray(vertices_lps_mm, float)
    method, off = "ransac", None
    face_normal, face_origin, share, width = _largest_plane(v, seed)
    normal, origin = face_normal, face_origin
    if fiducials_lps_mm is not None and len(fiducials_lps_mm) >= 3:
        f = np.asarray(fiducials_lps_mm, float)
        _, s, vt = np.linalg.svd(f - f.mean(0))
        if s[1] > 1e-3 * max(s[0], 1e-9):
            off = float(np.degrees(np.arccos(min(1.0, abs(float(vt[2] @ face_normal))))))
            rise = width * np.tan(np.radians(off))
            # the face's height is resolved to half a voxel across it: thick slices along
            # a tilted plate terrace the face, whose plane (0.44-0.52 degrees off on 5 mm
            # slices, review U) then rose 0.8-1.0 mm over exact markers
            bar = FACE_RISE_MM
            if voxel_mm is not None:
                bar = max(bar, 0.5 * voxel_depth_mm(voxel_mm, face_normal))
            if share < FACE_MIN_SHARE or (
                off <= FIDUCIALS_OFF_FACE_DEG
                and (
                    rise <= bar
                    or _band_share(v, vt[2], face_normal, face_origin)
                    >= FIDUCIALS_BAND_SHARE * share
                )
            ):
                normal, method, origin = vt[2], "fiducials", f.mean(0)
            else:
                log.warning(
                    "back plane: the fiducials' plane lies %.2f degrees off the surface's flat "
                    "back face (%.0f %% of the vertices, %.0f mm wide: it rises %.1f mm over "
                    "the fiducials' plane)%s The plane follows the face",
                    off,
                    100.0 * share,
                    width,
                    rise,
                    ": markers not on the plate?" if off > FIDUCIALS_OFF_FACE_DEG else ".",
                )
    normal = normal / np.linalg.norm(normal)
    h = (v - origin) @ normal
    parallel = abs(float(face_normal @ normal)) >= np.cos(np.radians(FIDUCIALS_OFF_FACE_DEG))
    # the body lies on the positive side of the plate: the side whose low end is a flat
    # face (the back face), where only one end is; else the side of most vertices seen from
    # the markers' plane (markers on posts above the body's mean height turned that away
    # from the body, the plane onto its apex: review U; a body wider at its top has the
    # larger flat face there, review V: its base is flat too, and the markers decide)
    flat = [_face_height(s * h) is not None for s in (1.0, -1.0)]
    if (not flat[0] and flat[1]) or (flat[0] == flat[1] and h.mean() < 0):
        normal, h = -normal, -h
    plane_h = None
    if parallel and share >= FACE_MIN_SHARE:  # the largest plane's height under the body
        m = v.mean(axis=0)
        plane_h = float((m - ((m - face_origin) @ face_normal) * face_normal - origin) @ normal)
    face = _face_height(h, plane_h)
    beyond = h < face - face_tol_mm if face is not None else np.zeros(len(h), bool)
    if beyond.any():
        log.warning(
            "back plane: %d surface vertices lie up to %.1f mm past the flat back face "
            "(tissue past the plate's edge); left out of its height",
            int(beyond.sum()),
            face - float(h.min()),
        )
    base = float(np.percentile(h[~beyond], 1.0))
    depth = None if voxel_mm is None else voxel_depth_mm(voxel_mm, normal)
    return BackPlane(origin + base * normal, normal, method, int(beyond.sum()), off, depth)


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = np.cross(normal, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


#: A smooth apex's cap fit is kept where the cap falls by at least this many times the
#: fit's rms residual (its noise) along its flattest direction at the cap's edge: on a
#: flat top, a cap that falls less places its "peak" by the noise (1.5-9 mm off the axis of
#: an 80 x 80 x 20 mm dome with 0.15-0.2 mm surface noise, on 8 mm caps).
CAP_FALL_OVER_NOISE = 4.0
#: Where no bump stands near the apex, one is looked for over the body's upper part: the
#: vertices at least this share of the apex's height above the plate (a nipple pointing
#: sideways, a phantom whose nipple is not on its top).
FAR_BUMP_HEIGHT_SHARE = 0.5
#: ... on a grid of this step (mm): one candidate per cell, the fit planes' cost bounded.
FAR_BUMP_GRID_MM = 2.0
#: Angular sectors around a far bump's tip: in every one the surface between half and the
#: whole fit radius must lie ``min_protrusion_mm`` below the tip (a peak), where a ridge
#: (a flat top's rounded rim, a bulge along the plate) stays level along its length.
FAR_BUMP_SECTORS = 8


def find_nipple(
    vertices_lps_mm: np.ndarray,
    plane: BackPlane,
    *,
    cap_radius_mm: float = 8.0,
    search_radius_mm: float = 12.0,
    fit_radius_mm: float = 10.0,
    tip_radius_mm: float = 3.0,
    min_protrusion_mm: float = 1.0,
) -> Nipple:
    """The nipple: the tip of the bump near the apex, or the apex of a bump-free body.

    The apex is the vertex farthest from the back plane. Under a lateral load the nipple
    tips over, so the apex is not the nipple's material tip (1.6-1.8 mm apart on the
    digital twin). Near the apex (``search_radius_mm``) each vertex's protrusion is its
    height above the plane fitted (PCA) to the surface within ``fit_radius_mm``; when the
    largest protrusion stands ``min_protrusion_mm`` above the median there (a bump), the
    tip is refined by a quadratic fit of the surface within ``tip_radius_mm`` of that
    vertex in its local frame (``quality["method"] = "protrusion"``). Where none does,
    a bump is looked for over the body's upper part (:data:`FAR_BUMP_HEIGHT_SHARE`, the
    same protrusion measure on a :data:`FAR_BUMP_GRID_MM` grid) that falls by
    ``min_protrusion_mm`` all around it (:data:`FAR_BUMP_SECTORS`; a ridge, such as a
    flat top's rounded rim, does not): a nipple off the top is its tip, with a warning
    (``quality["method"] = "far protrusion"``). Otherwise (a smooth dome) the apex is
    refined by a quadratic cap fit of the heights within ``cap_radius_mm`` in the plane
    coordinates (``"apex"``); where the top is too flat for that cap to fall clear of the
    noise (:data:`CAP_FALL_OVER_NOISE`), by the fit within twice, then four times the
    radius (``quality["cap_radius_mm"]``). A top flat even then keeps the highest vertex
    (``quality["refined"]`` False), with a warning.

    Parameters
    ----------
    vertices_lps_mm : (N, 3) float
        Surface vertices in the scan's LPS frame, mm.
    plane : BackPlane
        The back plane (:func:`estimate_back_plane`); heights are measured along its normal.
    cap_radius_mm : float
        Radius (mm, in the plane coordinates) of the quadratic cap fit at a bump-free
        apex; doubled, then quadrupled, on a flat top.
    search_radius_mm : float
        Radius (mm) around the apex searched for a bump.
    fit_radius_mm : float
        Radius (mm) of the local plane each vertex's protrusion is measured from.
    tip_radius_mm : float
        Radius (mm) of the quadratic fit that refines a bump's tip.
    min_protrusion_mm : float
        Protrusion (mm) above the median that makes a bump.

    Returns
    -------
    Nipple
        ``position_lps_mm`` (3,) in the scan's LPS frame (mm), ``height_mm`` above the
        back plane and the ``quality`` record described above.

    Raises
    ------
    SegmentationError
        No vertex lies above the back plane.
    """
    v = np.asarray(vertices_lps_mm, float)
    n = plane.normal
    h = (v - plane.point_lps_mm) @ n
    k = int(np.argmax(h))
    if h[k] <= 0:
        raise SegmentationError("no body above the back plane: cannot place the nipple")
    from scipy.spatial import cKDTree

    tree = cKDTree(v)
    near = np.asarray(tree.query_ball_point(v[k], search_radius_mm), dtype=int)
    frames, bump = _protrusions(v, tree, near, n, fit_radius_mm)
    j = int(np.argmax(bump))
    quality = {"protrusion_mm": float(bump[j] - np.median(bump)), "method": "apex"}
    tip_frame = None
    if quality["protrusion_mm"] >= min_protrusion_mm:
        tip_frame = v[near[j]], frames[j][1]
        quality["method"] = "protrusion"
    elif far := _far_bump(v, h, tree, n, fit_radius_mm, min_protrusion_mm):
        tip_frame, protrusion = far[:2], far[2]
        quality |= {"method": "far protrusion", "protrusion_mm": protrusion}
        log.warning(
            "no nipple bump within %.0f mm of the highest point; the nipple is a bump %.0f mm "
            "from it, %.0f mm lower (a nipple off the top of the body)",
            search_radius_mm,
            float(np.linalg.norm(far[0] - v[k])),
            float(h[k] - (far[0] - plane.point_lps_mm) @ n),
        )
    if tip_frame is not None:
        tip, frame = tip_frame
        pts = v[tree.query_ball_point(tip, tip_radius_mm)] - tip
        pos, q = _quadratic_peak(tip, pts, frame, tip_radius_mm)
        quality |= q
        if not q["refined"]:
            why = (
                f"found {len(pts)} surface vertices within {tip_radius_mm:g} mm of its top "
                "(it needs 10: a surface coarse for this body)"
                if len(pts) < 10
                else f"is no peak within {tip_radius_mm:g} mm of its top (not concave, or "
                "its peak off the fit)"
            )
            log.warning(
                "the nipple bump's tip fit %s: the nipple is that top vertex, good to the "
                "surface's vertex spacing",
                why,
            )
    else:
        e1, e2 = _plane_basis(n)
        lateral = np.linalg.norm(v - v[k] - np.outer(h - h[k], n), axis=1)
        for radius in cap_radius_mm * np.array([1.0, 2.0, 4.0]):  # a flatter top, a wider cap
            cap = (lateral <= radius) & (h > h[k] - min(2.0 * radius, 0.25 * h[k]))
            pos, q = _quadratic_peak(v[k], v[cap] - v[k], (e1, e2, n), radius)
            if q["refined"] and q["fall_mm"] >= CAP_FALL_OVER_NOISE * q["fit_rms_mm"]:
                break
        else:  # no cap falls clear of the noise: its peak is the noise's
            pos, q = v[k], q | {"refined": False}
        quality |= q | {"cap_radius_mm": float(radius)}
        if not q["refined"]:
            log.warning(
                "no nipple bump and no rounded apex within %.0f mm of the highest point: the "
                "nipple is that vertex (a flat-topped body has no distinct nipple)",
                radius,
            )
    quality["shift_from_apex_mm"] = float(np.linalg.norm(pos - v[k]))
    return Nipple(pos, float((pos - plane.point_lps_mm) @ n), quality)


def _far_bump(v, h, tree, normal, fit_radius_mm: float, min_protrusion_mm: float):
    """A bump over the body's upper part that falls all around: ``(tip, frame, mm)``.

    The candidates are the vertices at least :data:`FAR_BUMP_HEIGHT_SHARE` of the apex's
    height above the plate, one per :data:`FAR_BUMP_GRID_MM` cell; each one's protrusion
    is its height above the PCA plane of the surface within ``fit_radius_mm`` (as near the
    apex). The most protruding ones standing ``min_protrusion_mm`` above the candidates'
    median are tried in turn; the first whose surround falls in every sector
    (:func:`_falls_all_around`) is the bump. None where none does.
    """
    top = np.flatnonzero(h >= FAR_BUMP_HEIGHT_SHARE * h.max())
    _, first = np.unique(np.floor(v[top] / FAR_BUMP_GRID_MM), axis=0, return_index=True)
    cand = top[np.sort(first)]
    frames, bump = _protrusions(v, tree, cand, normal, fit_radius_mm)
    floor = float(np.median(bump)) + min_protrusion_mm
    for j in np.argsort(bump)[::-1]:
        if bump[j] < floor:
            return None
        tip, frame = v[cand[j]], frames[j][1]
        ring = v[tree.query_ball_point(tip, fit_radius_mm)] - tip
        if _falls_all_around(ring, frame, fit_radius_mm, min_protrusion_mm):
            return tip, frame, float(bump[j] - np.median(bump))
    return None


def _falls_all_around(d: np.ndarray, frame, radius_mm: float, fall_mm: float) -> bool:
    """Whether the surface falls ``fall_mm`` below a tip in every sector around it.

    ``d``: the surface's offsets from the tip (mm), ``frame`` its ``(e1, e2, normal)``;
    the sectors (:data:`FAR_BUMP_SECTORS`) span half to the whole ``radius_mm``.
    """
    e1, e2, e3 = frame
    u, w, z = d @ e1, d @ e2, d @ e3
    r = np.hypot(u, w)
    ring = (r >= 0.5 * radius_mm) & (r <= radius_mm)
    sector = np.floor((np.arctan2(w[ring], u[ring]) + np.pi) / (2 * np.pi) * FAR_BUMP_SECTORS)
    sector = np.minimum(sector.astype(int), FAR_BUMP_SECTORS - 1)
    highest = np.full(FAR_BUMP_SECTORS, np.inf)  # an empty sector: no fall seen
    seen = np.unique(sector)
    highest[seen] = -np.inf
    np.maximum.at(highest, sector, z[ring])
    return bool(np.all(highest <= -fall_mm))


def _protrusions(v, tree, idx, outward, fit_radius_mm: float):
    """Local frames and protrusions (mm) of the vertices ``idx``.

    A vertex's protrusion: its height above the PCA plane of the surface within
    ``fit_radius_mm`` of it.
    """
    frames = [_local_frame(v[tree.query_ball_point(v[i], fit_radius_mm)], outward) for i in idx]
    bump = np.array([(v[i] - c) @ f[2] for i, (c, f) in zip(idx, frames, strict=True)])
    return frames, bump


def _local_frame(points: np.ndarray, outward: np.ndarray):
    """Centroid and (e1, e2, normal) of a PCA plane; the normal along ``outward``."""
    c = points.mean(0)
    _, vec = np.linalg.eigh(np.cov((points - c).T))
    normal = vec[:, 0] * (1.0 if vec[:, 0] @ outward >= 0 else -1.0)
    return c, (vec[:, 2], vec[:, 1], normal)


def _quadratic_peak(origin: np.ndarray, d: np.ndarray, frame, radius_mm: float):
    """Stationary point of a concave quadratic fit of heights ``d . e3`` over ``(e1, e2)``."""
    e1, e2, e3 = frame
    u, w, hh = d @ e1, d @ e2, d @ e3
    quality = {"refined": False, "fit_rms_mm": float("nan"), "n_cap_vertices": len(d)}
    if len(d) < 10:
        return origin, quality
    X = np.stack([np.ones_like(u), u, w, u**2, u * w, w**2], 1)
    c, *_ = np.linalg.lstsq(X, hh, rcond=None)
    quality["fit_rms_mm"] = float(np.sqrt(np.mean((X @ c - hh) ** 2)))
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    if not np.all(np.linalg.eigvalsh(H) < 0):
        return origin, quality
    quality["fall_mm"] = float(-np.linalg.eigvalsh(H).max() / 2.0 * radius_mm**2)  # flattest
    x = np.linalg.solve(H, -c[1:3])
    if np.hypot(*x) > radius_mm:
        return origin, quality
    hx = c[0] + c[1] * x[0] + c[2] * x[1] + c[3] * x[0] ** 2 + c[4] * x[0] * x[1] + c[5] * x[1] ** 2
    quality["refined"] = True
    return origin + x[0] * e1 + x[1] * e2 + hx * e3, quality


def select_tumour(
    centres_lps_mm: np.ndarray, diameters_mm: np.ndarray, *, hint_lps_mm: np.ndarray | None = None
) -> int:
    """Index of the tracked tumour: the inclusion nearest to ``hint_lps_mm`` or the largest.

    Raises
    ------
    SegmentationError
        No inclusion to choose from.
    """
    c = np.asarray(centres_lps_mm, float).reshape(-1, 3)
    if len(c) == 0:
        raise SegmentationError("no inclusion found: cannot select the tracked tumour")
    if hint_lps_mm is None:
        return int(np.argmax(diameters_mm))
    return int(np.argmin(np.linalg.norm(c - np.asarray(hint_lps_mm, float), axis=1)))
