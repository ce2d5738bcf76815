"""Rigid surface refinement by open3d's point-to-plane ICP with a robust kernel.

No ICP is written here: each iteration is one call of
``open3d.pipelines.registration.registration_icp`` (so that iterations can be counted per
level), and the reported figures are open3d's own ``evaluate_registration`` at the final
transform.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from registration.errors import RegistrationError

__all__ = ["IcpLevel", "IcpResult", "icp_refine", "sample_triangles"]

#: Iterations over which a level at its cap must have stopped moving to count as settled
SETTLE_ITERATIONS = 10
#: ... and the largest change of its fitness (the share of points within the gate) there
SETTLE_FITNESS = 1e-3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IcpLevel:
    """One coarse-to-fine level of :func:`icp_refine`.

    Attributes
    ----------
    max_correspondence_distance_mm : float
        Correspondence gate of this level, millimetres.
    voxel_size_mm : float or None
        Voxel size used to downsample both clouds, or None (full resolution).
    kernel_scale_mm : float
        Scale parameter of the robust kernel, millimetres.
    iterations : int
        ICP iterations run.
    converged : bool
        Whether the change criterion was met before the iteration cap.
    settled : bool
        Converged, or at the cap with its fit no longer moving: the inlier RMSE within
        ``settle_mm`` and the fitness within :data:`SETTLE_FITNESS` over the last
        :data:`SETTLE_ITERATIONS` iterations (a surface that slides on itself, a round
        body about its axis, creeps by 1e-6 mm per iteration and never meets the change
        criterion, with figures that no longer move: review AO).
    fitness : float
        Open3d fitness at the end of the level (on the clouds of this level).
    inlier_rmse_mm : float
        Open3d inlier RMSE at the end of the level, millimetres.
    """

    max_correspondence_distance_mm: float
    voxel_size_mm: float | None
    kernel_scale_mm: float
    iterations: int
    converged: bool
    fitness: float
    inlier_rmse_mm: float
    settled: bool = True


@dataclass(frozen=True, eq=False)
class IcpResult:
    """Result of :func:`icp_refine`.

    Attributes
    ----------
    T_target_from_source : numpy.ndarray, shape (4, 4)
        Final transform mapping source mm to target mm (includes the initial transform).
    fitness : float
        Fraction of (masked, full-resolution) source points with a target point within
        ``evaluation_distance_mm`` -- open3d ``evaluate_registration`` at the final transform.
    inlier_rmse_mm : float
        RMS point-to-point distance of those inliers, millimetres (same evaluation).
    evaluation_distance_mm : float
        Correspondence distance of that evaluation (the last level's), millimetres.
    n_source_points : int
        Source points used (after the mask).
    n_correspondences : int
        Inlier correspondences in the final evaluation.
    levels : tuple of IcpLevel
        Per-level record, coarse to fine.
    """

    T_target_from_source: np.ndarray
    fitness: float
    inlier_rmse_mm: float
    evaluation_distance_mm: float
    n_source_points: int
    n_correspondences: int
    levels: tuple[IcpLevel, ...]

    def __post_init__(self) -> None:
        T = np.array(self.T_target_from_source, dtype=float, copy=True)
        T.flags.writeable = False
        object.__setattr__(self, "T_target_from_source", T)

    @property
    def iterations(self) -> tuple[int, ...]:
        """Iterations per level."""
        return tuple(lv.iterations for lv in self.levels)

    @property
    def converged(self) -> bool:
        """True when every level met its change criterion."""
        return all(lv.converged for lv in self.levels)

    @property
    def settled(self) -> bool:
        """True when every level settled (converged, or no longer moving at its cap)."""
        return all(lv.settled for lv in self.levels)


def _cloud(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    # open3d needs writeable float64 arrays (trimesh caches, e.g. vertex_normals, are not)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, dtype=np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.array(normals, dtype=np.float64))
    return pc


def _points(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3:
        raise RegistrationError(f"{name}: expected an (n >= 3, 3) array, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise RegistrationError(f"{name}: contains NaN or infinite coordinates")
    return p


def sample_triangles(
    vertices_mm: np.ndarray, faces: np.ndarray, *, spacing_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points on a triangle surface at most ``spacing_mm`` apart along its edges, with normals.

    Each face is split into ``k^2`` sub-triangles (``k`` = its longest edge over the
    spacing, rounded up) and their corners are kept, shared points once: an ICP target
    whose correspondence gates (1-2 mm) are finer than a coarse mesh's vertex spacing
    needs points where the surface is, not only at its vertices.

    Parameters
    ----------
    vertices_mm : array_like, shape (n, 3)
    faces : array_like of int, shape (f, 3)
    spacing_mm : float
        Largest spacing along an edge, mm (> 0).

    Returns
    -------
    points_mm : numpy.ndarray, shape (k, 3)
    normals : numpy.ndarray, shape (k, 3)
        Unit normal of the face each point was made from (sign as the face's winding).

    Raises
    ------
    RegistrationError
        Bad shapes, a non-positive spacing, or degenerate faces only.
    """
    v = np.asarray(vertices_mm, float)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or not len(f):
        raise RegistrationError(
            f"sample_triangles: vertices (n, 3) and faces (f, 3), got {v.shape}, {f.shape}"
        )
    if not spacing_mm > 0:
        raise RegistrationError(f"sample_triangles: spacing_mm must be positive, got {spacing_mm}")
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    keep = area2 > 0
    if not keep.any():
        raise RegistrationError("sample_triangles: every face is degenerate")
    tri, n = tri[keep], n[keep] / area2[keep, None]
    edge = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2).max(axis=1)
    k_of = np.maximum(np.ceil(edge / spacing_mm).astype(int), 1)
    points, normals = [], []
    for k in np.unique(k_of):
        sel = k_of == k
        ij = np.array([(i, j) for i in range(k + 1) for j in range(k + 1 - i)], float) / k
        bary = np.column_stack([1.0 - ij.sum(axis=1), ij])  # (b, 3)
        points.append(np.einsum("bc,fcd->fbd", bary, tri[sel]).reshape(-1, 3))
        normals.append(np.repeat(n[sel], len(bary), axis=0))
    P, N = np.vstack(points), np.vstack(normals)
    _, first = np.unique(np.round(P, 9), axis=0, return_index=True)  # shared edge points once
    first.sort()
    return P[first], N[first]


def _prepare(
    source_points_mm, target_points_mm, target_normals, source_mask, T_init
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    src = _points(source_points_mm, "source_points_mm")
    tgt = _points(target_points_mm, "target_points_mm")
    if source_mask is not None:
        mask = np.asarray(source_mask)
        if mask.dtype != bool or mask.shape != (src.shape[0],):
            raise RegistrationError(
                f"source_mask: expected a boolean array of shape ({src.shape[0]},), "
                f"got {mask.dtype} {mask.shape}"
            )
        src = src[mask]
        if src.shape[0] < 3:
            raise RegistrationError("source_mask leaves fewer than 3 source points")
    nrm = None
    if target_normals is not None:
        nrm = np.asarray(target_normals, dtype=float)
        if nrm.shape != tgt.shape:
            raise RegistrationError(f"target_normals: expected shape {tgt.shape}, got {nrm.shape}")
    T0 = np.eye(4) if T_init is None else np.array(T_init, dtype=float)
    if T0.shape != (4, 4):
        raise RegistrationError(f"T_init: expected shape (4, 4), got {T0.shape}")
    return src, tgt, nrm, T0


def _loss(kernel: str, scale: float):
    import open3d as o3d

    reg = o3d.pipelines.registration
    if kernel == "tukey":
        return reg.TukeyLoss(k=scale)
    if kernel == "huber":
        return reg.HuberLoss(k=scale)
    if kernel == "none":
        return reg.L2Loss()
    raise RegistrationError(f"kernel must be 'tukey', 'huber' or 'none', got {kernel!r}")


def _level_clouds(src, tgt, nrm, voxel, normal_knn):
    import open3d as o3d

    s = _cloud(src)
    t = _cloud(tgt, nrm)
    if voxel is not None:
        s = s.voxel_down_sample(voxel)
        t = t.voxel_down_sample(voxel)
    if nrm is None:
        t.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=normal_knn))
    else:
        t.normalize_normals()
    return s, t


def icp_refine(
    source_points_mm: np.ndarray,
    target_points_mm: np.ndarray,
    *,
    T_init: np.ndarray | None = None,
    target_normals: np.ndarray | None = None,
    source_mask: np.ndarray | None = None,
    max_correspondence_distances_mm: Sequence[float] = (10.0, 5.0, 2.0, 1.0),
    voxel_sizes_mm: Sequence[float | None] | None = None,
    kernel: Literal["tukey", "huber", "none"] = "tukey",
    kernel_scale_mm: float | None = None,
    max_iterations: int = 60,
    tolerance: float = 1e-6,
    settle_mm: float = 1e-4,
    normal_knn: int = 20,
) -> IcpResult:
    """Coarse-to-fine point-to-plane ICP (open3d) with a robust kernel.

    Parameters
    ----------
    source_points_mm : array_like, shape (n, 3)
        Moving points (e.g. a scan surface's vertices), source frame, millimetres.
    target_points_mm : array_like, shape (m, 3)
        Fixed points, target frame, millimetres.
    T_init : array_like, shape (4, 4), optional
        Initial ``T_target_from_source`` (e.g. the fiducial registration); default identity.
    target_normals : array_like, shape (m, 3), optional
        Target normals (sign irrelevant); estimated from ``normal_knn`` neighbours if absent.
    source_mask : array_like of bool, shape (n,), optional
        True for source points to use (e.g. False on the back plate).
    max_correspondence_distances_mm : sequence of float
        Correspondence gate per level, coarse to fine, millimetres.
    voxel_sizes_mm : sequence of float or None, optional
        Voxel size per level (same length) for downsampling both clouds; None = full cloud.
    kernel : {"tukey", "huber", "none"}
        Robust kernel on the point-to-plane residual.
    kernel_scale_mm : float, optional
        Kernel scale; default each level's correspondence distance.
    max_iterations : int
        Iteration cap per level.
    tolerance : float
        A level stops when fitness and inlier RMSE (mm) both change by less than this
        between iterations (open3d's default criterion and value).
    settle_mm : float
        A level at its cap is ``settled`` when its inlier RMSE moved by less than this
        (mm) over its last :data:`SETTLE_ITERATIONS` iterations (see :class:`IcpLevel`).
    normal_knn : int
        Neighbours for normal estimation.

    Returns
    -------
    IcpResult
        Final transform, open3d fitness and inlier RMSE at it, per-level iterations.

    Raises
    ------
    RegistrationError
        Bad shapes, or no correspondences within a level's gate.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, tgt, nrm, T = _prepare(
        source_points_mm, target_points_mm, target_normals, source_mask, T_init
    )
    dists = [float(d) for d in max_correspondence_distances_mm]
    if not dists or min(dists) <= 0:
        raise RegistrationError(f"max_correspondence_distances_mm must be positive: {dists}")
    voxels = [None] * len(dists) if voxel_sizes_mm is None else list(voxel_sizes_mm)
    if len(voxels) != len(dists):
        raise RegistrationError("voxel_sizes_mm must have one entry per correspondence distance")
    if max_iterations < 1:
        raise RegistrationError(f"max_iterations must be >= 1, got {max_iterations}")
    criteria = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
    levels = []
    for dist, voxel in zip(dists, voxels, strict=True):
        s, t = _level_clouds(src, tgt, nrm, voxel, normal_knn)
        scale = dist if kernel_scale_mm is None else float(kernel_scale_mm)
        est = reg.TransformationEstimationPointToPlane(_loss(kernel, scale))
        prev = reg.evaluate_registration(s, t, dist, T)
        if len(prev.correspondence_set) < 3:
            raise RegistrationError(
                f"ICP: no correspondences within {dist} mm at the start of a level; "
                "improve the initial transform or widen the gate"
            )
        converged, it, trail = False, 0, []
        while it < max_iterations:
            res = reg.registration_icp(s, t, dist, T, est, criteria)
            it += 1
            trail.append((res.inlier_rmse, res.fitness))
            T = np.asarray(res.transformation)
            if len(res.correspondence_set) < 3:
                raise RegistrationError(f"ICP lost all correspondences within {dist} mm")
            if (
                abs(res.fitness - prev.fitness) < tolerance
                and abs(res.inlier_rmse - prev.inlier_rmse) < tolerance
            ):
                converged = True
                break
            prev = res
        last = np.array(trail[-SETTLE_ITERATIONS:])
        settled = converged or (
            len(last) == SETTLE_ITERATIONS
            and np.ptp(last[:, 0]) < settle_mm
            and np.ptp(last[:, 1]) < SETTLE_FITNESS
        )
        levels.append(
            IcpLevel(
                dist,
                voxel,
                scale,
                it,
                converged,
                float(res.fitness),
                float(res.inlier_rmse),
                bool(settled),
            )
        )
        log.debug("ICP level %.3g mm: %d iterations, RMSE %.4f mm", dist, it, res.inlier_rmse)
    final = reg.evaluate_registration(_cloud(src), _cloud(tgt), dists[-1], T)
    return IcpResult(
        T_target_from_source=T,
        fitness=float(final.fitness),
        inlier_rmse_mm=float(final.inlier_rmse),
        evaluation_distance_mm=dists[-1],
        n_source_points=int(src.shape[0]),
        n_correspondences=len(final.correspondence_set),
        levels=tuple(levels),
    )
