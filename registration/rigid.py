"""Rigid point-set registration of fiducial markers and Fitzpatrick's target registration error.

The least-squares rotation is Arun, Huang & Blostein (1987) with Umeyama's (1991) reflection
correction: when the SVD solution is a reflection, the sign of the singular vector belonging to
the *smallest* singular value is flipped (for coplanar markers that is the plane normal, whose
sign the data cannot fix).  Expected target registration error follows Fitzpatrick, West &
Maurer (1998), IEEE TMI 17(5):694-702.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from registration.errors import (
    AmbiguousCorrespondenceError,
    DegenerateMarkersError,
    MarkerCountError,
    RegistrationError,
)

__all__ = ["Correspondence", "RigidFit", "apply_transform", "check_marker_geometry", "fit_rigid"]

#: How a scan's markers are paired with the reference's: in the order given, or by the
#: best-fitting permutation.
Correspondence = Literal["given", "auto"]

log = logging.getLogger(__name__)

#: Largest marker count for which ``correspondence="auto"`` tries every permutation (7! = 5040).
MAX_AUTO_MARKERS = 7


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.flags.writeable = False
    return a


def as_points(points: np.ndarray, *, name: str = "points") -> np.ndarray:
    """Validate and convert a point array.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Points in millimetres.
    name : str
        Name used in error messages.

    Returns
    -------
    numpy.ndarray, shape (n, 3)
        Float copy of the points.
    """
    p = np.array(points, dtype=float, copy=True)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MarkerCountError(f"{name}: expected an (n, 3) array of points, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise RegistrationError(f"{name}: contains NaN or infinite coordinates")
    return p


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4 x 4 homogeneous transform to points.

    Parameters
    ----------
    T : array_like, shape (4, 4)
        Homogeneous transform, e.g. ``T_ref_from_scan`` mapping scan-frame mm to ref-frame mm.
    points : array_like, shape (3,) or (n, 3)
        Points in the transform's source frame, millimetres.

    Returns
    -------
    numpy.ndarray, shape like ``points``
        Points in the transform's target frame, millimetres.

    Raises
    ------
    RegistrationError
        ``T`` is not 4 x 4, or the last dimension of ``points`` is not 3.
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise RegistrationError(f"transform: expected shape (4, 4), got {T.shape}")
    p = np.asarray(points, dtype=float)
    if p.shape[-1] != 3:
        raise RegistrationError(f"points: expected last dimension 3, got shape {p.shape}")
    return p @ T[:3, :3].T + T[:3, 3]


def check_marker_geometry(
    points_mm: np.ndarray,
    *,
    name: str = "markers",
    min_separation_mm: float = 1.0,
    min_line_offset_mm: float = 1.0,
) -> None:
    """Raise if a marker set cannot define a rigid transform.

    Parameters
    ----------
    points_mm : array_like, shape (n, 3)
        Marker positions, millimetres.
    name : str
        Name used in error messages (e.g. the scan name).
    min_separation_mm : float
        Two markers closer than this count as coincident (duplicated).
    min_line_offset_mm : float
        The RMS distance of the markers from their best-fit line must exceed this, otherwise
        the set is collinear and a rotation about that line is undetermined.

    Raises
    ------
    MarkerCountError
        Fewer than 3 markers or a wrongly shaped array.
    DegenerateMarkersError
        Coincident or collinear markers.
    """
    p = as_points(points_mm, name=name)
    n = p.shape[0]
    if n < 3:
        raise MarkerCountError(f"{name}: a rigid fit needs at least 3 markers, got {n}")
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    i, j = np.triu_indices(n, k=1)
    k = int(np.argmin(d[i, j]))
    if d[i[k], j[k]] < min_separation_mm:
        raise DegenerateMarkersError(
            f"{name}: markers {i[k]} and {j[k]} are {d[i[k], j[k]]:.3g} mm apart "
            f"(coincident or duplicated; need >= {min_separation_mm} mm)"
        )
    s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    offset = math.sqrt(float(s[1] ** 2 + s[2] ** 2) / n)
    if offset < min_line_offset_mm:
        raise DegenerateMarkersError(
            f"{name}: markers are collinear (RMS distance from their best-fit line "
            f"{offset:.3g} mm < {min_line_offset_mm} mm); the rotation about that line is "
            "undetermined"
        )


def _weighted_fit(p: np.ndarray, q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Arun/Umeyama fit: rotation R (3, 3) and translation t (3,) with q ~ R p + t."""
    w = w / w.sum()
    pc = w @ p
    qc = w @ q
    H = (p - pc).T @ ((q - qc) * w[:, None])  # 3 x 3 cross-covariance, source x target
    U, S, Vt = np.linalg.svd(H)
    d = np.ones(3)
    if np.linalg.det(Vt.T @ U.T) < 0.0:
        # Umeyama: flip the singular vector of the smallest singular value, wherever it is.
        d[int(np.argmin(S))] = -1.0
    R = Vt.T @ np.diag(d) @ U.T
    return R, qc - R @ pc


@dataclass(frozen=True, eq=False)
class RigidFit:
    """Result of a rigid fiducial fit ``target ~ R @ source + t``.

    Attributes
    ----------
    T_target_from_source : numpy.ndarray, shape (4, 4)
        Homogeneous transform mapping source-frame mm to target-frame mm.
    fre_mm : float
        Fiducial registration error: RMS of ``residuals_mm`` (unweighted), millimetres.
    residuals_mm : numpy.ndarray, shape (n,)
        Distance of each mapped source marker from its target marker, millimetres, in source
        marker order.
    permutation : tuple of int
        ``source[i]`` corresponds to ``target[permutation[i]]``.
    source_points_mm : numpy.ndarray, shape (n, 3)
        The source markers (source frame, mm), kept for :meth:`tre_mm`.
    second_best_fre_mm : float or None
        With ``correspondence="auto"``, the FRE of the runner-up ordering (an ambiguity margin).
    """

    T_target_from_source: np.ndarray
    fre_mm: float
    residuals_mm: np.ndarray
    permutation: tuple[int, ...]
    source_points_mm: np.ndarray
    second_best_fre_mm: float | None = None

    def __post_init__(self) -> None:
        for f in ("T_target_from_source", "residuals_mm", "source_points_mm"):
            object.__setattr__(self, f, _frozen(getattr(self, f)))

    @property
    def rotation(self) -> np.ndarray:
        """Rotation matrix, shape (3, 3), det +1."""
        return self.T_target_from_source[:3, :3]

    @property
    def translation_mm(self) -> np.ndarray:
        """Translation, shape (3,), millimetres."""
        return self.T_target_from_source[:3, 3]

    @property
    def n_markers(self) -> int:
        """Number of markers N."""
        return int(self.source_points_mm.shape[0])

    @property
    def fle_estimate_mm(self) -> float:
        """Fiducial localisation error estimated from the FRE: FLE^2 = FRE^2 N / (N - 2).

        NaN for N < 3 markers.  With N = 3 the estimate rests on only three residual degrees
        of freedom and is noisy; pass a known FLE to :meth:`tre_mm` where available.
        """
        n = self.n_markers
        if n <= 2:
            return float("nan")
        return self.fre_mm * math.sqrt(n / (n - 2))

    def rotation_sd_deg(self, *, fle_mm: float | None = None) -> float:
        """Standard deviation of the fitted rotation about its weakest principal axis, degrees.

        The rotation part of Fitzpatrick, West & Maurer's TRE: a rotation ``dtheta_k`` about
        the k-th principal axis moves a point at distance ``d_k`` by ``d_k dtheta_k``, so
        ``var(dtheta_k) = FLE^2 / (3 N f_k^2)`` (``f_k`` the markers' RMS distance from
        that axis); the largest over the axes. Markers nearly on one line leave the
        rotation about it, and with it a scan's gravity direction, uncertain.

        Parameters
        ----------
        fle_mm : float, optional
            Fiducial localisation error (RMS, 3D); default :attr:`fle_estimate_mm`.

        Returns
        -------
        float
            Degrees; NaN with fewer than three markers.
        """
        fle = self.fle_estimate_mm if fle_mm is None else float(fle_mm)
        if self.n_markers < 3 or not np.isfinite(fle):
            return float("nan")
        _, _, f2 = self._principal_axes()
        return float(np.degrees(fle / np.sqrt(3.0 * self.n_markers * f2.min())))

    def _principal_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centroid (3,), principal axes (rows of Vt, (3, 3)) and each axis's f_k^2 (3,).

        ``f_k`` is the markers' RMS distance from the k-th principal axis (the TRE's).
        """
        m = self.source_points_mm
        c = m.mean(axis=0)
        _, _, Vt = np.linalg.svd(m - c)
        x = (m - c) @ Vt.T  # markers in principal-axis coordinates, (N, 3)
        return c, Vt, np.mean(np.sum(x**2, axis=1, keepdims=True) - x**2, axis=0)

    def tre_mm(self, points_mm: np.ndarray, *, fle_mm: float | None = None) -> np.ndarray | float:
        """Return the expected target registration error (Fitzpatrick, West & Maurer 1998).

        ``TRE^2(r) = FLE^2 / N * (1 + 1/3 * sum_k d_k^2 / f_k^2)`` where ``d_k`` is the
        distance of ``r`` from the k-th principal axis of the marker configuration and ``f_k``
        the RMS distance of the markers from that axis.

        Parameters
        ----------
        points_mm : array_like, shape (3,) or (m, 3)
            Target points in the *source* frame, millimetres.
        fle_mm : float, optional
            Fiducial localisation error (RMS, 3D); default :attr:`fle_estimate_mm`.

        Returns
        -------
        float or numpy.ndarray, shape (m,)
            Expected RMS TRE at each point, millimetres.

        Raises
        ------
        RegistrationError
            ``points_mm`` is not of shape (3,) or (m, 3).
        """
        fle = self.fle_estimate_mm if fle_mm is None else float(fle_mm)
        r = np.asarray(points_mm, dtype=float)
        single = r.ndim == 1
        r = np.atleast_2d(r)
        if r.shape[1] != 3:
            raise RegistrationError(f"tre_mm: expected (m, 3) points, got shape {r.shape}")
        c, Vt, f2 = self._principal_axes()
        y = (r - c) @ Vt.T  # targets in principal-axis coordinates, (m, 3)
        d2 = np.sum(y**2, axis=1, keepdims=True) - y**2  # (m, 3)
        tre = np.sqrt(fle**2 / self.n_markers * (1.0 + np.sum(d2 / f2, axis=1) / 3.0))
        return float(tre[0]) if single else tre


def _homogeneous(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4 x 4 transform of rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _plate_side(fits: list, normals, margin: float, name: str) -> list:
    """The fits that turn the source plate's normal onto the target's side (not a flip)."""
    n_src, n_tgt = (np.reshape(np.asarray(x, dtype=float), 3) for x in normals)
    kept = [f for f in fits if float((f[2] @ n_src) @ n_tgt) > 0.0]
    if not kept:
        raise RegistrationError(
            f"{name}: every marker ordering flips the body through the plate (the plates' "
            "normals point the other way after every fit): check the back planes"
        )
    if kept[0][0] > fits[0][0] + margin:
        raise RegistrationError(
            f"{name}: the best-fitting marker ordering {fits[0][1]} (FRE {fits[0][0]:.3f} mm) "
            f"flips the body through the plate, and the best that does not, {kept[0][1]}, "
            f"fits worse (FRE {kept[0][0]:.3f} mm): the markers and the back plane disagree"
        )
    return kept


def _break_tie(fits: list, below: float, tie_break, margin: float, said: str) -> tuple:
    """The fit among those with an FRE below ``below`` whose ``tie_break`` is clearly least."""
    close = [f for f in fits if f[0] < below]
    scores = [float(tie_break(_homogeneous(f[2], f[3]))) for f in close]
    if not np.all(np.isfinite(scores)):
        raise AmbiguousCorrespondenceError(f"{said}, and the other data's mismatch is {scores}")
    order = np.argsort(scores)
    best, rival = scores[order[0]], scores[order[1]]
    if rival - best < margin or rival < 2.0 * best:
        raise AmbiguousCorrespondenceError(
            f"{said}, and the other data tell them apart by {best:.2f} against {rival:.2f} "
            f"mm (needed: {margin} mm and twice); use markers with distinct pairwise "
            "distances or give the order"
        )
    chosen = close[order[0]]
    log.warning(
        "%s; taken: ordering %s, the other data's mismatch %.2f mm (next %.2f mm)",
        said,
        chosen[1],
        best,
        rival,
    )
    return chosen


def fit_rigid(
    source_points: np.ndarray,
    target_points: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    correspondence: Correspondence = "given",
    ambiguity_margin_mm: float = 1.0,
    max_fre_mm: float | None = None,
    min_separation_mm: float = 1.0,
    min_line_offset_mm: float = 1.0,
    plate_normals: tuple[np.ndarray, np.ndarray] | None = None,
    tie_break: Callable[[np.ndarray], float] | None = None,
    name: str = "markers",
) -> RigidFit:
    """Least-squares rigid transform between two marker sets.

    Parameters
    ----------
    source_points : array_like, shape (n, 3)
        Markers in the source frame (e.g. a scan's LPS), millimetres.
    target_points : array_like, shape (n, 3)
        Markers in the target frame (e.g. the reference scan's LPS), millimetres.
    weights : array_like, shape (n,), optional
        Non-negative weights per source marker (e.g. inverse localisation variance).
    correspondence : {"given", "auto"}
        ``"given"``: row i of the source matches row i of the target.  ``"auto"``: the order
        is unknown; every permutation (n <= 7) is fitted and the smallest residual kept.
    ambiguity_margin_mm : float
        With ``"auto"``, the runner-up ordering must have an FRE at least this much larger
        than the best, otherwise the correspondence is ambiguous (e.g. an isosceles layout).
    max_fre_mm : float, optional
        Raise if the final FRE exceeds this (a missing or spurious marker).
    min_separation_mm, min_line_offset_mm : float
        Degeneracy thresholds, see :func:`check_marker_geometry`.
    plate_normals : (array_like of shape (3,), array_like of shape (3,)), optional
        With ``"auto"``, the back plate's unit normal pointing into the body in the source
        and in the target frame (:class:`imaging.BackPlane` ``normal``). An ordering
        whose rotation turns the source normal away from the target's flips the body
        through the plate and is no candidate: a layout with a mirror line (an isosceles
        triangle or trapezoid) fits that flip as well as the true ordering. Where the best
        fit is such a flip by more than ``ambiguity_margin_mm``, markers and planes
        disagree: :class:`RegistrationError`. A turn in the plate (of a rectangle, say)
        keeps the normal: see ``tie_break``.
    tie_break : callable, optional
        With ``"auto"``, where orderings fit within ``ambiguity_margin_mm`` of the best,
        a mismatch in mm of the transform ``T_target_from_source`` (4, 4) by other data
        (e.g. the body's footprint on the plate, which a turn of a square layout moves):
        the ordering of the lowest mismatch is taken where every other's is at least
        ``ambiguity_margin_mm`` and twice larger; otherwise the correspondence stays
        ambiguous.
    name : str
        Name used in error messages (e.g. the scan name).

    Returns
    -------
    RigidFit
        Transform ``T_target_from_source`` (det R = +1), FRE, residuals and permutation.

    Raises
    ------
    MarkerCountError
        Fewer than 3 markers, count mismatch, bad weights shape.
    DegenerateMarkersError
        Coincident or collinear markers in either set.
    AmbiguousCorrespondenceError
        ``"auto"`` cannot tell two orderings apart.
    RegistrationError
        Non-finite input, bad weights, FRE above ``max_fre_mm``.
    """
    p = as_points(source_points, name=f"{name} (source)")
    q = as_points(target_points, name=f"{name} (target)")
    if p.shape[0] != q.shape[0]:
        raise MarkerCountError(
            f"{name}: marker count mismatch, source has {p.shape[0]} and target {q.shape[0]}"
        )
    geo = dict(min_separation_mm=min_separation_mm, min_line_offset_mm=min_line_offset_mm)
    check_marker_geometry(p, name=f"{name} (source)", **geo)
    check_marker_geometry(q, name=f"{name} (target)", **geo)
    n = p.shape[0]
    w = _check_weights(weights, n, name)

    if correspondence == "given":
        perms = [tuple(range(n))]
    elif correspondence == "auto":
        if n > MAX_AUTO_MARKERS:
            raise MarkerCountError(
                f"{name}: automatic correspondence supports at most {MAX_AUTO_MARKERS} markers, "
                f"got {n}; give the markers in corresponding order"
            )
        perms = list(itertools.permutations(range(n)))
    else:
        raise RegistrationError(f"correspondence must be 'given' or 'auto', got {correspondence!r}")

    fits = []
    for perm in perms:
        qp = q[list(perm)]
        R, t = _weighted_fit(p, qp, w)
        res = np.linalg.norm(p @ R.T + t - qp, axis=1)
        fits.append((float(np.sqrt(np.mean(res**2))), perm, R, t, res))
    fits.sort(key=lambda f: f[0])
    if plate_normals is not None and len(fits) > 1:
        fits = _plate_side(fits, plate_normals, ambiguity_margin_mm, name)
    fre, perm, R, t, res = fits[0]
    second = fits[1][0] if len(fits) > 1 else None
    if second is not None and second - fre < ambiguity_margin_mm:
        said = (
            f"{name}: marker correspondence is ambiguous: orderings {perm} and {fits[1][1]} "
            f"give FRE {fre:.3f} and {second:.3f} mm (margin {ambiguity_margin_mm} mm)"
        )
        if tie_break is None:
            raise AmbiguousCorrespondenceError(
                f"{said}; use markers with distinct pairwise distances or give the order"
            )
        fre, perm, R, t, res = _break_tie(
            fits, fre + ambiguity_margin_mm, tie_break, ambiguity_margin_mm, said
        )
        second = min(f[0] for f in fits if f[1] != perm)
    if max_fre_mm is not None and fre > max_fre_mm:
        raise RegistrationError(
            f"{name}: fiducial registration error {fre:.3f} mm exceeds {max_fre_mm} mm "
            f"(per-marker residuals {np.round(res, 3).tolist()} mm); a marker may be missing "
            "or spurious"
        )
    log.debug("%s: FRE %.3f mm, permutation %s", name, fre, perm)
    return RigidFit(
        T_target_from_source=_homogeneous(R, t),
        fre_mm=fre,
        residuals_mm=res,
        permutation=tuple(int(i) for i in perm),
        source_points_mm=p,
        second_best_fre_mm=second,
    )


def _check_weights(weights: np.ndarray | None, n: int, name: str) -> np.ndarray:
    if weights is None:
        return np.ones(n)
    w = np.asarray(weights, dtype=float)
    if w.shape != (n,):
        raise MarkerCountError(f"{name}: weights must have shape ({n},), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise RegistrationError(f"{name}: weights must be finite and non-negative")
    if np.count_nonzero(w) < 3:
        raise RegistrationError(f"{name}: at least 3 markers need a positive weight")
    return w
