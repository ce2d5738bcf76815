"""Register every scan of a session to the reference scan by its fiducial markers."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from registration.distance_metrics import closest_point_distances, point_to_surface_distances
from registration.errors import MarkerCountError, RegistrationError
from registration.gravity import angle_between_deg, check_posture, gravity_in_reference
from registration.rigid import Correspondence, apply_transform, fit_rigid

__all__ = [
    "ScanRegistration",
    "footprint_mismatch_mm",
    "format_registration_table",
    "register_scans",
]

log = logging.getLogger(__name__)
#: A registration whose rotation is this uncertain (1 sd, degrees) is warned about: a
#: degree of gravity direction turns sin(1 deg) = 1.7 % of the load across the phantom.
ROTATION_SD_WARN_DEG = 1.0


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.flags.writeable = False
    return a


def _opt(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass(frozen=True, eq=False)
class ScanRegistration:
    """Fiducial registration of one scan to the reference scan.

    Attributes
    ----------
    scan : str
        Scan name.
    is_reference : bool
        True for the reference scan (identity transform, zero errors by definition).
    T_ref_from_scan : numpy.ndarray, shape (4, 4)
        Maps the scan's LPS mm to the reference scan's LPS mm.
    fre_mm : float
        Fiducial registration error (RMS over markers), millimetres.
    tre_nipple_mm, tre_tumour_mm : float or None
        Expected target registration error (Fitzpatrick) at the scan's nipple / tumour,
        millimetres; None where the landmark is not given.
    gravity_ref : numpy.ndarray, shape (3,)
        Unit gravity vector of this scan in the reference frame.
    residuals_mm : numpy.ndarray, shape (k,)
        Per-marker residuals in the scan's marker order, millimetres.
    permutation : tuple of int
        Scan marker i corresponds to reference marker ``permutation[i]``.
    fle_mm : float
        Fiducial localisation error used for the TRE (given or estimated from the FRE).
    rotation_sd_deg : float
        Standard deviation of the registration's rotation about its weakest axis, degrees
        (:meth:`registration.RigidFit.rotation_sd_deg`; 0 for the reference): the
        uncertainty of the scan's gravity direction that the markers leave.
    """

    scan: str
    is_reference: bool
    T_ref_from_scan: np.ndarray
    fre_mm: float
    tre_nipple_mm: float | None
    tre_tumour_mm: float | None
    gravity_ref: np.ndarray
    residuals_mm: np.ndarray
    permutation: tuple[int, ...]
    fle_mm: float
    rotation_sd_deg: float = 0.0

    def __post_init__(self) -> None:
        for f in ("T_ref_from_scan", "gravity_ref", "residuals_mm"):
            object.__setattr__(self, f, _frozen(getattr(self, f)))

    def to_json(self) -> dict:
        """Plain JSON-ready dict (lists and floats; None for a missing TRE).

        Returns
        -------
        dict
            Keys ``T_ref_from_scan``, ``fre_mm``, ``tre_nipple_mm``, ``tre_tumour_mm``,
            ``gravity_ref``, plus ``residuals_mm``, ``marker_permutation``, ``fle_mm``,
            ``rotation_sd_deg``, ``is_reference``, ``frame`` and ``tre_method``.
        """
        return {
            "T_ref_from_scan": self.T_ref_from_scan.tolist(),
            "fre_mm": float(self.fre_mm),
            "tre_nipple_mm": _opt(self.tre_nipple_mm),
            "tre_tumour_mm": _opt(self.tre_tumour_mm),
            "gravity_ref": self.gravity_ref.tolist(),
            "residuals_mm": self.residuals_mm.tolist(),
            "marker_permutation": list(self.permutation),
            "fle_mm": _opt(self.fle_mm),
            "rotation_sd_deg": _opt(self.rotation_sd_deg),
            "is_reference": bool(self.is_reference),
            "frame": "fiducial",
            "tre_method": "Fitzpatrick, West & Maurer 1998 (expected RMS)",
        }


def _gravity_for(scan: str, gravity_scanner) -> np.ndarray:
    if isinstance(gravity_scanner, dict):
        if scan not in gravity_scanner:
            raise RegistrationError(f"gravity_scanner: no entry for scan {scan!r}")
        return np.asarray(gravity_scanner[scan], dtype=float)
    return np.asarray(gravity_scanner, dtype=float)


def footprint_mismatch_mm(a, b) -> float:
    """Symmetric mean distance between two footprints (mm).

    Parameters
    ----------
    a, b : array_like, shape (k, 3), or tuple of (array_like (v, 3), array_like (f, 3))
        Points, millimetres, or triangle patches ``(vertices_mm, faces)``.

    Returns
    -------
    float
        The mean of each footprint's mean distance to the other: of its points to the
        other's nearest point
        (:func:`registration.distance_metrics.closest_point_distances`), or, where both
        are patches, of its vertices to the other's triangles
        (:func:`registration.distance_metrics.point_to_surface_distances`), which does not
        take two samplings of one surface for a distance.
    """
    if isinstance(a, tuple) and isinstance(b, tuple):
        ab = point_to_surface_distances(a[0], *b, signed=False).mean()
        return 0.5 * float(ab + point_to_surface_distances(b[0], *a, signed=False).mean())
    a, b = (x[0] if isinstance(x, tuple) else x for x in (a, b))
    ab = closest_point_distances(a, b).mean()
    return 0.5 * float(ab + closest_point_distances(b, a).mean())


def _both(by_scan: dict | None, scan: str, reference: str) -> bool:
    return bool(by_scan) and scan in by_scan and reference in by_scan


def _footprint_tie(scan, ref):
    def mismatch(T: np.ndarray) -> float:
        if isinstance(scan, tuple):
            return footprint_mismatch_mm((apply_transform(T, scan[0]), scan[1]), ref)
        return footprint_mismatch_mm(apply_transform(T, scan), ref)

    return mismatch


def register_scans(
    fiducials_by_scan: dict[str, np.ndarray],
    *,
    reference: str,
    gravity_scanner: Sequence[float] | dict[str, Sequence[float]] = (0.0, 1.0, 0.0),
    nominal_angles_deg: dict[str, float] | None = None,
    nominal_gravity: dict[str, Sequence[float]] | None = None,
    landmarks_by_scan: dict[str, dict[str, np.ndarray]] | None = None,
    plate_normals_by_scan: dict[str, np.ndarray] | None = None,
    footprints_by_scan: dict[str, np.ndarray | tuple] | None = None,
    correspondence: Correspondence = "auto",
    fle_mm: float | None = None,
    max_fre_mm: float | None = 2.0,
    ambiguity_margin_mm: float = 1.0,
    posture_warn_deg: float = 2.0,
    posture_error_deg: float = 10.0,
) -> dict[str, ScanRegistration]:
    """Register every scan to the reference scan by its fiducial markers.

    Parameters
    ----------
    fiducials_by_scan : dict of str to array_like, shape (k, 3)
        Marker centroids per scan in that scan's LPS frame, millimetres (any order with
        ``correspondence="auto"``).
    reference : str
        Name of the reference scan (its LPS frame is the ref frame, the model's).
    gravity_scanner : array_like, shape (3,), or dict of str to it
        Gravity direction in the scanner LPS frame, for all scans or per scan.
    nominal_angles_deg : dict of str to float, optional
        Nominal posture angles (one common rotation plane); checked against the registered
        gravity with :func:`registration.gravity.check_posture`.
    nominal_gravity : dict of str to array_like, shape (3,), optional
        Instead of ``nominal_angles_deg`` (postures in several planes): nominal gravity
        directions in one common frame, checked the same way.
    landmarks_by_scan : dict of str to dict of str to array_like, shape (3,), optional
        Per scan, ``"nipple"`` and/or ``"tumour"`` in the scan's LPS frame, millimetres; the
        TRE is evaluated there.
    plate_normals_by_scan : dict of str to array_like, shape (3,), optional
        Per scan, the back plate's unit normal pointing into the body in the scan's LPS
        frame: orderings that flip the body through the plate are no candidates
        (``plate_normals`` of :func:`registration.rigid.fit_rigid`).
    footprints_by_scan : dict of str to array_like (k, 3) or tuple, optional
        Per scan, points of the body's back face on the plate in the scan's LPS frame
        (it does not move between postures), or its triangles ``(vertices_mm, faces)``.
        Where orderings of a symmetric layout fit alike, the one that lays the scan's
        footprint onto the reference's is taken
        (:func:`footprint_mismatch_mm`, the ``tie_break`` of ``fit_rigid``).
    correspondence : {"auto", "given"}
        Marker correspondence, see :func:`registration.rigid.fit_rigid`.
    fle_mm : float, optional
        Known fiducial localisation error for the TRE; default estimated from each FRE.
    max_fre_mm : float or None
        Raise if a scan's FRE exceeds this (missing or spurious marker); None disables.
    ambiguity_margin_mm : float
        See :func:`registration.rigid.fit_rigid`.
    posture_warn_deg, posture_error_deg : float
        Thresholds of the posture cross-check.

    Returns
    -------
    dict of str to ScanRegistration
        Per scan, in input order.

    Raises
    ------
    RegistrationError
        Unknown reference, bad markers (see ``fit_rigid``), posture mismatch.
    MarkerCountError
        A scan's marker array differs in shape from the reference scan's (a
        :class:`RegistrationError`).
    PostureMismatchError
        The registered gravities contradict the nominal postures by more than
        ``posture_error_deg`` (a :class:`RegistrationError`).
    """
    if reference not in fiducials_by_scan:
        raise RegistrationError(
            f"reference scan {reference!r} has no fiducials (scans: {sorted(fiducials_by_scan)})"
        )
    ref_markers = np.asarray(fiducials_by_scan[reference], dtype=float)
    landmarks_by_scan = landmarks_by_scan or {}
    out: dict[str, ScanRegistration] = {}
    for scan, markers in fiducials_by_scan.items():
        markers = np.asarray(markers, dtype=float)
        if markers.ndim != 2 or markers.shape != ref_markers.shape:
            raise MarkerCountError(
                f"scan {scan!r}: markers have shape {markers.shape}, the reference scan "
                f"{reference!r} has {ref_markers.shape}"
            )
        normals = tie = None
        if _both(plate_normals_by_scan, scan, reference):
            normals = (plate_normals_by_scan[scan], plate_normals_by_scan[reference])
        if _both(footprints_by_scan, scan, reference) and scan != reference:
            tie = _footprint_tie(footprints_by_scan[scan], footprints_by_scan[reference])
        fit = fit_rigid(
            markers,
            ref_markers,
            correspondence="given" if scan == reference else correspondence,
            max_fre_mm=max_fre_mm,
            ambiguity_margin_mm=ambiguity_margin_mm,
            plate_normals=normals,
            tie_break=tie,
            name=f"scan {scan!r}",
        )
        is_ref = scan == reference
        T = np.eye(4) if is_ref else fit.T_target_from_source
        fle = 0.0 if is_ref else (fit.fle_estimate_mm if fle_mm is None else float(fle_mm))
        tre = {}
        for key in ("nipple", "tumour"):
            point = landmarks_by_scan.get(scan, {}).get(key)
            if point is None:
                tre[key] = None
            else:
                tre[key] = 0.0 if is_ref else fit.tre_mm(np.reshape(point, 3), fle_mm=fle)
        out[scan] = ScanRegistration(
            scan=scan,
            is_reference=is_ref,
            T_ref_from_scan=T,
            fre_mm=0.0 if is_ref else fit.fre_mm,
            tre_nipple_mm=tre["nipple"],
            tre_tumour_mm=tre["tumour"],
            gravity_ref=gravity_in_reference(T, _gravity_for(scan, gravity_scanner)),
            residuals_mm=np.zeros(len(markers)) if is_ref else fit.residuals_mm,
            permutation=tuple(range(len(markers))) if is_ref else fit.permutation,
            fle_mm=fle,
            rotation_sd_deg=0.0 if is_ref else fit.rotation_sd_deg(fle_mm=fle),
        )
        log.info("registered %s: FRE %.3f mm", scan, out[scan].fre_mm)
        if out[scan].rotation_sd_deg > ROTATION_SD_WARN_DEG:
            log.warning(
                "scan %r: the fiducials leave the registration's rotation about their "
                "weakest axis uncertain by %.1f degrees (1 sd; markers nearly on one line?): "
                "the scan's gravity direction, and the posture, are uncertain by as much",
                scan,
                out[scan].rotation_sd_deg,
            )
    if nominal_angles_deg or nominal_gravity:
        check_posture(
            {s: r.gravity_ref for s, r in out.items()},
            nominal_angles_deg or None,
            nominal_gravity=nominal_gravity or None,
            warn_deg=posture_warn_deg,
            error_deg=posture_error_deg,
        )
    return out


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "-" if x is None else format(x, spec)


def format_registration_table(
    registrations: dict[str, ScanRegistration], *, roles: dict[str, str] | None = None
) -> str:
    """Plain-text summary table of a session's registrations for the CLI.

    Parameters
    ----------
    registrations : dict of str to ScanRegistration
        Output of :func:`register_scans`.
    roles : dict of str to str, optional
        Each scan's role for the role column; default "reference" for the reference
        scan and blank for the others.

    Returns
    -------
    str
        One header line, a rule and one line per scan (FRE, TRE at nipple and tumour in mm,
        gravity in the reference frame and its 3-D angle to the reference scan's gravity,
        unlike ``validate``'s posture: the angle within the posture's plane).
    """
    ref = next((r for r in registrations.values() if r.is_reference), None)
    header = [
        "scan",
        "role",
        "FRE mm",
        "TRE nipple mm",
        "TRE tumour mm",
        "gravity_ref",
        "angle to ref g, deg",  # 3-D; validate's posture is the in-plane angle
    ]
    rows = []
    for name, r in registrations.items():
        angle = None if ref is None else angle_between_deg(r.gravity_ref, ref.gravity_ref)
        rows.append(
            [
                name,
                (roles or {}).get(name, "reference" if r.is_reference else ""),
                _fmt(r.fre_mm, ".3f"),
                _fmt(r.tre_nipple_mm),
                _fmt(r.tre_tumour_mm),
                "[" + ", ".join(f"{g:+.3f}" for g in r.gravity_ref) + "]",
                _fmt(angle),
            ]
        )
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=True)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(lines)
