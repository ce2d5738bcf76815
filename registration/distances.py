"""Surface and landmark distances, each tagged with the frame it was measured in.

``frame="fiducial"``: the two geometries are compared as placed by the fiducial registration.
``frame="icp"``: the moving geometry is first re-aligned onto the fixed one by ICP.  ICP
absorbs part of any real shape difference into a rigid motion, so ICP-frame errors are biased
low; report both.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from registration.distance_metrics import (
    FRAMES,
    DistanceSummary,
    Frame,
    _check_frame,
    _pts,
    closest_point_distances,
    hausdorff_mm,
    point_to_surface_distances,
    summarise,
)
from registration.errors import RegistrationError
from registration.rigid import apply_transform

__all__ = [
    "FRAMES",
    "DistanceSummary",
    "Frame",
    "PointDistance",
    "SurfaceDistances",
    "closest_point_distances",
    "hausdorff_mm",
    "landmark_errors",
    "nipple_error",
    "point_to_surface_distances",
    "summarise",
    "surface_errors",
]


@dataclass(frozen=True, eq=False)
class SurfaceDistances:
    """Distances from a moving surface's points to a fixed surface, in one frame.

    Attributes
    ----------
    frame : {"fiducial", "icp"}
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

    frame: Frame
    method: str
    summary: DistanceSummary
    hausdorff_mm: float
    distances_mm: np.ndarray
    T_applied: np.ndarray


@dataclass(frozen=True)
class PointDistance:
    """Error of one point (nipple, tumour, ...) in one frame.

    Attributes
    ----------
    name : str
        What was measured (e.g. ``"nipple"``).
    frame : {"fiducial", "icp"}
    method : str
        ``"closest_point"`` (to the other surface) or ``"landmark"`` (to the other landmark).
    error_mm : float
        Distance, millimetres.
    """

    name: str
    frame: Frame
    method: str
    error_mm: float


def _fixed_from_moving(T_fixed_from_moving, T_icp) -> np.ndarray | None:
    """The ICP transform given by its name, or by its former name ``T_icp`` (deprecated)."""
    if T_icp is None:
        return T_fixed_from_moving
    if T_fixed_from_moving is not None:
        raise RegistrationError("give T_fixed_from_moving, not also T_icp (its former name)")
    warnings.warn(
        "T_icp is now T_fixed_from_moving (the frames in its name)",
        DeprecationWarning,
        stacklevel=4,  # the caller of the public function (through _transforms)
    )
    return T_icp


def _transforms(
    frames: Sequence[Frame], T_fixed_from_moving: np.ndarray | None, T_icp=None, icp=None
) -> dict:
    T_fixed_from_moving = _fixed_from_moving(T_fixed_from_moving, T_icp)
    out = {}
    for fr in frames:
        _check_frame(fr)
        if fr == "fiducial":
            out[fr] = np.eye(4)
        elif T_fixed_from_moving is not None:
            out[fr] = np.asarray(T_fixed_from_moving, dtype=float)
        elif icp is not None:
            out[fr] = icp()
        else:
            raise RegistrationError("frame 'icp' requested but no T_fixed_from_moving given")
    return out


def surface_errors(
    moving_points_mm: np.ndarray,
    fixed_vertices_mm: np.ndarray,
    fixed_faces: np.ndarray | None = None,
    *,
    frames: Sequence[Frame] = FRAMES,
    T_fixed_from_moving: np.ndarray | None = None,
    T_icp: np.ndarray | None = None,
    fixed_mask: np.ndarray | None = None,
    icp_options: dict | None = None,
) -> dict[str, SurfaceDistances]:
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
    T_fixed_from_moving : array_like, shape (4, 4), optional
        ICP transform moving -> fixed; computed by :func:`registration.icp.icp_refine` from
        the identity when ``"icp"`` is requested and this is None.
    T_icp : array_like, shape (4, 4), optional
        Its former name (deprecated: a DeprecationWarning).
    fixed_mask : array_like of bool, shape (m,), optional
        Fixed vertices that the Hausdorff distance may reach (e.g. False on the back plate
        when the moving points exclude it); distances and ICP use the whole fixed surface.
    icp_options : dict, optional
        Keyword arguments for ``icp_refine``.

    Returns
    -------
    dict of str to SurfaceDistances
        Keyed by frame.

    Raises
    ------
    RegistrationError
        A point array is not a non-empty finite (n, 3) array, ``fixed_mask`` is not bool
        of shape (m,), ``fixed_faces`` is malformed, or a frame is unknown.
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
    for fr, T in _transforms(frames, T_fixed_from_moving, T_icp, run_icp).items():
        moved = apply_transform(T, mov)
        if fixed_faces is None:
            d, method = closest_point_distances(moved, fix), "point_to_point"
        else:
            d, method = point_to_surface_distances(moved, fix, fixed_faces), "point_to_surface"
        out[fr] = SurfaceDistances(
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
    frames: Sequence[Frame] = FRAMES,
    T_fixed_from_moving: np.ndarray | None = None,
    T_icp: np.ndarray | None = None,
) -> dict[str, PointDistance]:
    """Compute the dissertation's nipple error: closest point-to-point distance of the nipple.

    Parameters
    ----------
    nipple_mm : array_like, shape (3,)
        Nipple of the moving surface (e.g. the simulated nipple node), millimetres.
    surface_points_mm : array_like, shape (m, 3)
        Points of the fixed surface (e.g. the measured surface), same frame, millimetres.
    frames : sequence of {"fiducial", "icp"}
        Frames to report.
    T_fixed_from_moving : array_like, shape (4, 4), optional
        ICP transform moving -> fixed (required for ``"icp"``), applied to the nipple.
    T_icp : array_like, shape (4, 4), optional
        Its former name (deprecated: a DeprecationWarning).

    Returns
    -------
    dict of str to PointDistance
        Keyed by frame.

    Raises
    ------
    RegistrationError
        A frame is unknown, ``"icp"`` is requested without ``T_fixed_from_moving``, both
        it and ``T_icp`` are given, or ``nipple_mm`` or
        ``surface_points_mm`` is not finite or not of its shape.
    """
    nipple = np.asarray(nipple_mm, dtype=float)
    if nipple.size != 3:  # review BJ: the reshape's own ValueError came first
        raise RegistrationError(f"nipple_mm must be one point (3,), got shape {nipple.shape}")
    p = _pts(nipple.reshape(1, 3), "nipple_mm")
    out = {}
    for fr, T in _transforms(frames, T_fixed_from_moving, T_icp).items():
        d = float(closest_point_distances(apply_transform(T, p), surface_points_mm)[0])
        out[fr] = PointDistance("nipple", fr, "closest_point", d)
    return out


def landmark_errors(
    moving_by_name: dict[str, np.ndarray],
    fixed_by_name: dict[str, np.ndarray],
    *,
    frames: Sequence[Frame] = ("fiducial",),
    T_fixed_from_moving: np.ndarray | None = None,
    T_icp: np.ndarray | None = None,
) -> dict[str, dict[str, PointDistance]]:
    """Landmark-to-landmark distances (e.g. nipple and tumour centre) for common names.

    Parameters
    ----------
    moving_by_name : dict of str to array_like, shape (3,)
        Moving landmarks (e.g. predicted), millimetres.
    fixed_by_name : dict of str to array_like, shape (3,)
        Fixed landmarks (e.g. measured), same frame, millimetres.
    frames : sequence of {"fiducial", "icp"}
        Frames to report.
    T_fixed_from_moving : array_like, shape (4, 4), optional
        ICP transform moving -> fixed (required for ``"icp"``).
    T_icp : array_like, shape (4, 4), optional
        Its former name (deprecated: a DeprecationWarning).

    Returns
    -------
    dict of str to dict of str to PointDistance
        ``result[frame][name]``.

    Raises
    ------
    RegistrationError
        A frame is unknown, ``"icp"`` is requested without ``T_fixed_from_moving``, or
        both it and ``T_icp`` are given.
    """
    names = [n for n in moving_by_name if n in fixed_by_name]
    out: dict[str, dict[str, PointDistance]] = {}
    for fr, T in _transforms(frames, T_fixed_from_moving, T_icp).items():
        out[fr] = {}
        for n in names:
            a = apply_transform(T, np.asarray(moving_by_name[n], dtype=float).reshape(3))
            b = np.asarray(fixed_by_name[n], dtype=float).reshape(3)
            out[fr][n] = PointDistance(n, fr, "landmark", float(np.linalg.norm(a - b)))
    return out


#: Former names of :class:`SurfaceDistances` and :class:`PointDistance`, kept importable
#: (review BJ: records named like exceptions, beside ``imaging.SurfaceError``, which is one)
SurfaceError = SurfaceDistances
PointError = PointDistance
