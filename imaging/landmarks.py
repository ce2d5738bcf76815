"""Landmarks: the back-plate plane, the nipple and the tracked tumour."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from imaging.errors import SegmentationError

__all__ = ["BackPlane", "Nipple", "estimate_back_plane", "find_nipple", "select_tumour"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class BackPlane:
    """Back-plate plane.

    ``point_lps_mm`` (3,) on the body's flat back face, unit ``normal``
    (3,) pointing from the plate into the body, and ``method`` ("fiducials" or "ransac").
    """

    point_lps_mm: np.ndarray
    normal: np.ndarray
    method: str


@dataclass(frozen=True, eq=False)
class Nipple:
    """Nipple estimate.

    ``position_lps_mm`` (3,), ``height_mm`` above the back plane,
    ``quality`` (``refined``, ``fit_rms_mm``, ``n_cap_vertices``, ``shift_from_apex_mm``).
    """

    position_lps_mm: np.ndarray
    height_mm: float
    quality: dict = field(default_factory=dict)


def estimate_back_plane(
    vertices_lps_mm: np.ndarray, *, fiducials_lps_mm: np.ndarray | None = None, seed: int = 0
) -> BackPlane:
    """Estimate the back-plate plane of a body surface.

    With three or more non-collinear fiducials (which sit on the plate) the normal is the
    normal of their best-fit plane; otherwise it is the largest plane found by RANSAC on the
    surface vertices (the flat back face). The normal is oriented towards the body and the
    plane is moved onto the body's back face (the 1st percentile of vertex heights).
    """
    v = np.asarray(vertices_lps_mm, float)
    method = "ransac"
    if fiducials_lps_mm is not None and len(fiducials_lps_mm) >= 3:
        f = np.asarray(fiducials_lps_mm, float)
        _, s, vt = np.linalg.svd(f - f.mean(0))
        if s[1] > 1e-3 * max(s[0], 1e-9):
            normal, method, origin = vt[2], "fiducials", f.mean(0)
    if method == "ransac":
        import open3d as o3d

        o3d.utility.random.seed(seed)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(v))
        (a, b, c, d), _ = pc.segment_plane(0.5, 3, 1000)
        normal = np.array([a, b, c], float)
        origin = -d * normal / float(normal @ normal)
    normal = normal / np.linalg.norm(normal)
    h = (v - origin) @ normal
    if h.mean() < 0:  # the body lies on the positive side of the plate
        normal, h = -normal, -h
    base = float(np.percentile(h, 1.0))
    return BackPlane(origin + base * normal, normal, method)


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.eye(3)[np.argmin(np.abs(normal))]
    e1 = np.cross(normal, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def find_nipple(
    vertices_lps_mm: np.ndarray, plane: BackPlane, *, cap_radius_mm: float = 8.0
) -> Nipple:
    """Apex of the body relative to the back plane, refined by a quadratic cap fit.

    The vertex farthest from the plane is found first; the heights of the vertices within
    ``cap_radius_mm`` (in-plane) of it are fitted by a quadratic in the plane coordinates and
    the stationary point of a concave fit (inside the cap) is returned.
    """
    v = np.asarray(vertices_lps_mm, float)
    n = plane.normal
    h = (v - plane.point_lps_mm) @ n
    k = int(np.argmax(h))
    apex = v[k]
    if h[k] <= 0:
        raise SegmentationError("no body above the back plane: cannot place the nipple")
    e1, e2 = _plane_basis(n)
    d = v - apex
    u, w = d @ e1, d @ e2
    near = (u**2 + w**2 <= cap_radius_mm**2) & (h > h[k] - 2.0 * cap_radius_mm)
    quality = {"refined": False, "fit_rms_mm": float("nan"), "n_cap_vertices": int(near.sum())}
    pos = apex
    if near.sum() >= 10:
        uu, ww, hh = u[near], w[near], h[near]
        X = np.stack([np.ones_like(uu), uu, ww, uu**2, uu * ww, ww**2], 1)
        c, *_ = np.linalg.lstsq(X, hh, rcond=None)
        H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
        if np.all(np.linalg.eigvalsh(H) < 0):
            x = np.linalg.solve(H, -c[1:3])
            if np.hypot(*x) <= cap_radius_mm:
                hx = c[0] + c[1] * x[0] + c[2] * x[1] + c[3] * x[0] ** 2
                hx += c[4] * x[0] * x[1] + c[5] * x[1] ** 2
                pos = apex + x[0] * e1 + x[1] * e2 + (hx - h[k]) * n
                quality["refined"] = True
        quality["fit_rms_mm"] = float(np.sqrt(np.mean((X @ c - hh) ** 2)))
    quality["shift_from_apex_mm"] = float(np.linalg.norm(pos - apex))
    return Nipple(pos, float((pos - plane.point_lps_mm) @ n), quality)


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
