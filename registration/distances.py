"""Surface and landmark distances, each tagged with the frame it was measured in.

``frame="fiducial"``: the two geometries are compared as placed by the fiducial registration.
``frame="icp"``: the moving geometry is first re-aligned onto the fixed one by ICP.  ICP
absorbs part of any real shape difference into a rigid motion, so ICP-frame errors are biased
low; report both.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from registration.errors import RegistrationError
from registration.rigid import apply_transform

__all__ = [
    "FRAMES",
    "DistanceSummary",
    "PointError",
    "SurfaceError",
    "closest_point_distances",
    "hausdorff_mm",
    "landmark_errors",
    "nipple_error",
    "point_to_surface_distances",
    "summarise",
    "surface_errors",
]

log = logging.getLogger(__name__)

#: Frames an error can be measured in.
FRAMES = ("fiducial", "icp")


def _check_frame(frame: str) -> str:
    if frame not in FRAMES:
        raise RegistrationError(f"frame must be one of {FRAMES}, got {frame!r}")
    return frame


def _pts(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise RegistrationError(f"{name}: expected a non-empty (n, 3) array, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise RegistrationError(f"{name}: contains NaN or infinite coordinates")
    return p


@dataclass(frozen=True)
class DistanceSummary:
    """Summary statistics of distances (millimetres) measured in one frame.

    Attributes
    ----------
    frame : str
        ``"fiducial"`` or ``"icp"``.
    n : int
        Number of distances.
    mean_mm, sd_mm, median_mm, p95_mm, max_mm, rms_mm : float
        Mean, sample standard deviation (ddof 1; 0 for n = 1), median, 95th percentile,
        maximum and root mean square of the distances as given (signed stay signed).
    """

    frame: str
    n: int
    mean_mm: float
    sd_mm: float
    median_mm: float
    p95_mm: float
    max_mm: float
    rms_mm: float

    def to_json(self) -> dict:
        """Plain dict for JSON output."""
        return dict(self.__dict__)


def summarise(distances_mm: np.ndarray, *, frame: str = "fiducial") -> DistanceSummary:
    """Summarise distances.

    Parameters
    ----------
    distances_mm : array_like, shape (n,)
        Distances in millimetres (take ``abs`` first for unsigned statistics).
    frame : {"fiducial", "icp"}
        Frame the distances were measured in.

    Returns
    -------
    DistanceSummary
        Mean, sd, median, p95, max, RMS and count.
    """
    d = np.asarray(distances_mm, dtype=float).ravel()
    if d.size == 0 or not np.all(np.isfinite(d)):
        raise RegistrationError("summarise: need a non-empty array of finite distances")
    return DistanceSummary(
        frame=_check_frame(frame),
        n=int(d.size),
        mean_mm=float(d.mean()),
        sd_mm=float(d.std(ddof=1)) if d.size > 1 else 0.0,
        median_mm=float(np.median(d)),
        p95_mm=float(np.percentile(d, 95)),
        max_mm=float(d.max()),
        rms_mm=float(np.sqrt(np.mean(d**2))),
    )


def closest_point_distances(
    points_mm: np.ndarray, target_points_mm: np.ndarray, *, return_index: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Distance from each point to the closest target point (scipy cKDTree).

    Parameters
    ----------
    points_mm : array_like, shape (n, 3)
        Query points, millimetres.
    target_points_mm : array_like, shape (m, 3)
        Target points in the same frame, millimetres.
    return_index : bool
        Also return the index of the closest target point.

    Returns
    -------
    numpy.ndarray, shape (n,)
        Distances, millimetres (and indices, shape (n,), if requested).
    """
    from scipy.spatial import cKDTree

    p = _pts(points_mm, "points_mm")
    t = _pts(target_points_mm, "target_points_mm")
    d, idx = cKDTree(t).query(p, k=1)
    return (d, idx) if return_index else d


def hausdorff_mm(a_points_mm: np.ndarray, b_points_mm: np.ndarray) -> float:
    """Symmetric Hausdorff distance between two point sets, millimetres.

    Parameters
    ----------
    a_points_mm, b_points_mm : array_like, shape (n, 3) and (m, 3)
        Point sets in one frame, millimetres.

    Returns
    -------
    float
        ``max(max_a min_b |a - b|, max_b min_a |a - b|)``.
    """
    return float(
        max(
            closest_point_distances(a_points_mm, b_points_mm).max(),
            closest_point_distances(b_points_mm, a_points_mm).max(),
        )
    )


def point_to_surface_distances(
    points_mm: np.ndarray, vertices_mm: np.ndarray, faces: np.ndarray, *, signed: bool = True
) -> np.ndarray:
    """Distance from points to a triangle mesh (open3d RaycastingScene closest points).

    The sign is that of ``(p - closest) . n_face`` with the face normal from the triangle
    winding (right-hand rule): positive on the side the normals point to (outside for an
    outward-wound surface).  Open surfaces are fine.  Near vertices of saddle-shaped regions
    the face normal may give the wrong sign for points off the surface by more than the
    local feature size.

    Parameters
    ----------
    points_mm : array_like, shape (n, 3)
        Query points, millimetres.
    vertices_mm : array_like, shape (v, 3)
        Mesh vertices in the same frame, millimetres.
    faces : array_like of int, shape (f, 3)
        Triangles (vertex indices).
    signed : bool
        Return signed distances; otherwise absolute.

    Returns
    -------
    numpy.ndarray, shape (n,)
        Distances, millimetres (float32 ray-casting precision, ~1e-5 mm at 100 mm).
    """
    import open3d as o3d

    p = _pts(points_mm, "points_mm")
    v = _pts(vertices_mm, "vertices_mm")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise RegistrationError(f"faces: expected a non-empty (f, 3) array, got shape {f.shape}")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise RegistrationError(f"faces: indices must lie in [0, {v.shape[0]})")
    origin = v.mean(axis=0)  # centre before float32 to keep precision
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((v - origin).astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32))
    )
    ans = scene.compute_closest_points(o3d.core.Tensor((p - origin).astype(np.float32)))
    diff = (p - origin) - ans["points"].numpy().astype(float)
    d = np.linalg.norm(diff, axis=1)
    if not signed:
        return d
    tri = v[f[ans["primitive_ids"].numpy().astype(np.int64)]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    s = np.sign(np.einsum("ij,ij->i", diff, n))
    return np.where(s < 0, -d, d)


@dataclass(frozen=True, eq=False)
class SurfaceError:
    """Distances from a moving surface's points to a fixed surface, in one frame.

    Attributes
    ----------
    frame : str
        ``"fiducial"`` or ``"icp"``.
    method : str
        ``"point_to_point"`` (closest fixed point) or ``"point_to_surface"`` (signed, to mesh).
    summary : DistanceSummary
        Statistics of the absolute distances.
    hausdorff_mm : float
        Symmetric Hausdorff distance between the (transformed) moving points and the fixed
        vertices (those in ``fixed_mask``), millimetres.
    distances_mm : numpy.ndarray, shape (n,)
        Per moving point distance (signed for ``point_to_surface``), millimetres.
    T_applied : numpy.ndarray, shape (4, 4)
        Transform applied to the moving points before measuring (identity for fiducial).
    """

    frame: str
    method: str
    summary: DistanceSummary
    hausdorff_mm: float
    distances_mm: np.ndarray
    T_applied: np.ndarray


@dataclass(frozen=True)
class PointError:
    """Error of one point (nipple, tumour, ...) in one frame.

    Attributes
    ----------
    name : str
        What was measured (e.g. ``"nipple"``).
    frame : str
        ``"fiducial"`` or ``"icp"``.
    method : str
        ``"closest_point"`` (to the other surface) or ``"landmark"`` (to the other landmark).
    error_mm : float
        Distance, millimetres.
    """

    name: str
    frame: str
    method: str
    error_mm: float


def _transforms(frames: Sequence[str], T_icp: np.ndarray | None, icp=None) -> dict:
    out = {}
    for fr in frames:
        _check_frame(fr)
        if fr == "fiducial":
            out[fr] = np.eye(4)
        elif T_icp is not None:
            out[fr] = np.asarray(T_icp, dtype=float)
        elif icp is not None:
            out[fr] = icp()
        else:
            raise RegistrationError("frame 'icp' requested but no T_icp given")
    return out


def surface_errors(
    moving_points_mm: np.ndarray,
    fixed_vertices_mm: np.ndarray,
    fixed_faces: np.ndarray | None = None,
    *,
    frames: Sequence[str] = FRAMES,
    T_icp: np.ndarray | None = None,
    fixed_mask: np.ndarray | None = None,
    icp_options: dict | None = None,
) -> dict[str, SurfaceError]:
    """Surface error of a moving point set against a fixed surface, in one or both frames.

    Parameters
    ----------
    moving_points_mm : array_like, shape (n, 3)
        Moving points (e.g. the measured surface without the back plate), millimetres, already
        in the fixed surface's frame by the fiducial registration.
    fixed_vertices_mm : array_like, shape (m, 3)
        Fixed surface vertices (e.g. the simulated surface), millimetres.
    fixed_faces : array_like of int, shape (f, 3), optional
        Fixed triangles; given: signed point-to-surface distances, else closest point.
    frames : sequence of {"fiducial", "icp"}
        Frames to report.
    T_icp : array_like, shape (4, 4), optional
        ICP transform moving -> fixed; computed by :func:`registration.icp.icp_refine` from
        the identity when ``"icp"`` is requested and this is None.
    fixed_mask : array_like of bool, shape (m,), optional
        Fixed vertices that the Hausdorff distance may reach (e.g. False on the back plate
        when the moving points exclude it); distances and ICP use the whole fixed surface.
    icp_options : dict, optional
        Keyword arguments for ``icp_refine``.

    Returns
    -------
    dict of str to SurfaceError
        Keyed by frame.
    """
    mov = _pts(moving_points_mm, "moving_points_mm")
    fix = _pts(fixed_vertices_mm, "fixed_vertices_mm")
    fix_h = fix
    if fixed_mask is not None:
        fm = np.asarray(fixed_mask)
        if fm.dtype != bool or fm.shape != (fix.shape[0],):
            raise RegistrationError(f"fixed_mask: expected bool of shape ({fix.shape[0]},)")
        fix_h = fix[fm]

    def run_icp() -> np.ndarray:
        from registration.icp import icp_refine

        normals = None
        if fixed_faces is not None:
            import trimesh

            normals = trimesh.Trimesh(fix, fixed_faces, process=False).vertex_normals
        res = icp_refine(mov, fix, target_normals=normals, **(icp_options or {}))
        return np.asarray(res.T_target_from_source)

    out = {}
    for fr, T in _transforms(frames, T_icp, run_icp).items():
        moved = apply_transform(T, mov)
        if fixed_faces is None:
            d, method = closest_point_distances(moved, fix), "point_to_point"
        else:
            d, method = point_to_surface_distances(moved, fix, fixed_faces), "point_to_surface"
        out[fr] = SurfaceError(
            frame=fr,
            method=method,
            summary=summarise(np.abs(d), frame=fr),
            hausdorff_mm=hausdorff_mm(moved, fix_h),
            distances_mm=d,
            T_applied=T,
        )
    return out


def nipple_error(
    nipple_mm: np.ndarray,
    surface_points_mm: np.ndarray,
    *,
    frames: Sequence[str] = FRAMES,
    T_icp: np.ndarray | None = None,
) -> dict[str, PointError]:
    """Compute the dissertation's nipple error: closest point-to-point distance of the nipple.

    Parameters
    ----------
    nipple_mm : array_like, shape (3,)
        Nipple of the moving surface (e.g. the simulated nipple node), millimetres.
    surface_points_mm : array_like, shape (m, 3)
        Points of the fixed surface (e.g. the measured surface), same frame, millimetres.
    frames : sequence of {"fiducial", "icp"}
        Frames to report.
    T_icp : array_like, shape (4, 4), optional
        ICP transform moving -> fixed (required for ``"icp"``), applied to the nipple.

    Returns
    -------
    dict of str to PointError
        Keyed by frame.
    """
    p = _pts(np.reshape(nipple_mm, (1, 3)), "nipple_mm")
    out = {}
    for fr, T in _transforms(frames, T_icp).items():
        d = float(closest_point_distances(apply_transform(T, p), surface_points_mm)[0])
        out[fr] = PointError("nipple", fr, "closest_point", d)
    return out


def landmark_errors(
    moving_by_name: dict[str, np.ndarray],
    fixed_by_name: dict[str, np.ndarray],
    *,
    frames: Sequence[str] = ("fiducial",),
    T_icp: np.ndarray | None = None,
) -> dict[str, dict[str, PointError]]:
    """Landmark-to-landmark distances (e.g. nipple and tumour centre) for common names.

    Parameters
    ----------
    moving_by_name : dict of str to array_like, shape (3,)
        Moving landmarks (e.g. predicted), millimetres.
    fixed_by_name : dict of str to array_like, shape (3,)
        Fixed landmarks (e.g. measured), same frame, millimetres.
    frames : sequence of {"fiducial", "icp"}
        Frames to report.
    T_icp : array_like, shape (4, 4), optional
        ICP transform moving -> fixed (required for ``"icp"``).

    Returns
    -------
    dict of str to dict of str to PointError
        ``result[frame][name]``.
    """
    names = [n for n in moving_by_name if n in fixed_by_name]
    out: dict[str, dict[str, PointError]] = {}
    for fr, T in _transforms(frames, T_icp).items():
        out[fr] = {}
        for n in names:
            a = apply_transform(T, np.asarray(moving_by_name[n], dtype=float).reshape(3))
            b = np.asarray(fixed_by_name[n], dtype=float).reshape(3)
            out[fr][n] = PointError(n, fr, "landmark", float(np.linalg.norm(a - b)))
    return out
