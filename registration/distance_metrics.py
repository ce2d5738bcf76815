"""Point-set and point-to-surface distances and their summary statistics.

The building blocks of :mod:`registration.distances`, which re-exports every public
name here; all distances are in millimetres, measured in the frame the inputs share.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from registration.errors import RegistrationError

__all__ = [
    "FRAMES",
    "DistanceSummary",
    "Frame",
    "closest_point_distances",
    "hausdorff_mm",
    "point_to_surface_distances",
    "summarise",
]

#: A frame an error can be measured in (see :mod:`registration.distances`).
Frame = Literal["fiducial", "icp"]
#: Frames an error can be measured in.
FRAMES: tuple[Frame, ...] = get_args(Frame)


def _check_frame(frame: str) -> Frame:
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
    frame : {"fiducial", "icp"}
    n : int
        Number of distances.
    mean_mm, sd_mm, median_mm, p95_mm, max_mm, rms_mm : float
        Mean, sample standard deviation (ddof 1; 0 for n = 1), median, 95th percentile,
        maximum and root mean square of the distances as given (signed stay signed).
    """

    frame: Frame
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


def summarise(distances_mm: np.ndarray, *, frame: Frame = "fiducial") -> DistanceSummary:
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

    Raises
    ------
    RegistrationError
        ``distances_mm`` is empty or not finite, or ``frame`` is unknown.
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

    Raises
    ------
    RegistrationError
        Either point set is not a non-empty finite (n, 3) array.
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

    Raises
    ------
    RegistrationError
        Either point set is not a non-empty finite (n, 3) array.
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

    Raises
    ------
    RegistrationError
        ``points_mm`` or ``vertices_mm`` is not a non-empty finite (n, 3) array, or
        ``faces`` is not a non-empty (f, 3) array of indices into ``vertices_mm``.
    """
    import open3d as o3d

    p = _pts(points_mm, "points_mm")
    v = _pts(vertices_mm, "vertices_mm")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise RegistrationError(f"faces: expected a non-empty (f, 3) array, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):  # review BK: an IndexError from open3d's side
        raise RegistrationError(f"faces: expected integer vertex indices, got {f.dtype}")
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
