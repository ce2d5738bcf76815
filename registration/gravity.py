"""Gravity direction of each scan in the ref frame (the reference scan's LPS), posture checks."""

from __future__ import annotations

import itertools
import logging
import math
import warnings
from dataclasses import dataclass

import numpy as np

from registration.errors import PostureMismatchError, PostureMismatchWarning, RegistrationError

__all__ = ["PostureCheck", "angle_between_deg", "check_posture", "gravity_in_reference"]

log = logging.getLogger(__name__)


def _unit(v: np.ndarray, *, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise RegistrationError(f"{name}: expected a finite 3-vector, got {v!r}")
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise RegistrationError(f"{name}: zero vector has no direction")
    return v / norm


def gravity_in_reference(
    T_ref_from_scan: np.ndarray, gravity_scanner: np.ndarray = (0.0, 1.0, 0.0)
) -> np.ndarray:
    """Gravity of one scan expressed in the ref frame (the reference scan's LPS).

    Parameters
    ----------
    T_ref_from_scan : array_like, shape (4, 4) or (3, 3)
        Transform (or its rotation) mapping the scan's LPS frame to the reference scan's LPS.
    gravity_scanner : array_like, shape (3,)
        Gravity direction in the scanner's LPS frame (normalised here); default
        ``(0, 1, 0)``, the +P (posterior) axis, as in session.toml's ``[scanner] gravity``.

    Returns
    -------
    numpy.ndarray, shape (3,)
        Unit gravity vector ``R_ref_from_scan @ gravity_scanner`` in the ref frame.

    Raises
    ------
    RegistrationError
        ``T_ref_from_scan`` is neither (4, 4) nor (3, 3), or ``gravity_scanner`` (or its
        image) is not a finite non-zero 3-vector.
    """
    T = np.asarray(T_ref_from_scan, dtype=float)
    if T.shape not in ((4, 4), (3, 3)):
        raise RegistrationError(f"T_ref_from_scan: expected (4, 4) or (3, 3), got {T.shape}")
    g = _unit(gravity_scanner, name="gravity_scanner")
    return _unit(T[:3, :3] @ g, name="gravity_ref")


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two 3-vectors in degrees, in [0, 180] (atan2 form, accurate near 0).

    Parameters
    ----------
    a, b : array_like, shape (3,)
        Non-zero vectors (any length, any common frame).

    Returns
    -------
    float
        Angle in degrees.

    Raises
    ------
    RegistrationError
        ``a`` or ``b`` is not a finite non-zero 3-vector.
    """
    ua = _unit(a, name="a")
    ub = _unit(b, name="b")
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(ua, ub))), float(ua @ ub)))


def _nominal_difference_deg(a_deg: float, b_deg: float) -> float:
    """Unsigned difference of two posture angles folded into [0, 180]."""
    d = abs(float(a_deg) - float(b_deg)) % 360.0
    return min(d, 360.0 - d)


@dataclass(frozen=True)
class PostureCheck:
    """Comparison of a measured gravity angle with the nominal posture difference.

    Attributes
    ----------
    scan_a, scan_b : str
        The two scans compared.
    measured_deg : float
        Angle between their registered gravity vectors (reference frame), degrees.
    nominal_deg : float
        Difference of their nominal posture angles folded into [0, 180], degrees.
    discrepancy_deg : float
        ``abs(measured_deg - nominal_deg)``, degrees.
    status : str
        ``"ok"``, ``"warn"`` or ``"error"``.
    """

    scan_a: str
    scan_b: str
    measured_deg: float
    nominal_deg: float
    discrepancy_deg: float
    status: str


def check_posture(
    gravity_ref_by_scan: dict[str, np.ndarray],
    nominal_angles_deg: dict[str, float] | None = None,
    *,
    nominal_gravity: dict[str, np.ndarray] | None = None,
    warn_deg: float = 2.0,
    error_deg: float = 10.0,
) -> list[PostureCheck]:
    """Cross-check registered gravity directions against nominal postures.

    For every pair of scans that both have a nominal posture, the angle between their
    registered gravity vectors must equal the angle between their nominal gravities: the
    difference of their nominal angles for rotations in one common plane
    (``nominal_angles_deg``), or the angle between nominal directions given in any one
    common frame (``nominal_gravity``: postures in several planes).

    Parameters
    ----------
    gravity_ref_by_scan : dict of str to array_like, shape (3,)
        Gravity per scan in the reference frame.
    nominal_angles_deg : dict of str to float, optional
        Nominal posture angle per scan (one common plane), degrees; scans missing here are
        not checked.
    nominal_gravity : dict of str to array_like, shape (3,), optional
        Instead of ``nominal_angles_deg``: nominal gravity direction per scan in one common
        frame (any length); scans missing here are not checked.
    warn_deg : float
        Discrepancy above which a :class:`PostureMismatchWarning` is issued.
    error_deg : float
        Discrepancy above which :class:`PostureMismatchError` is raised.

    Returns
    -------
    list of PostureCheck
        One entry per checked pair.

    Raises
    ------
    PostureMismatchError
        Some pair disagrees by more than ``error_deg``; the message lists every such pair.
    RegistrationError
        A nominal posture names a scan without a gravity vector, both or neither kinds of
        nominal posture are given, or thresholds are invalid.
    """
    if not 0.0 <= warn_deg <= error_deg:
        raise RegistrationError(f"need 0 <= warn_deg <= error_deg, got {warn_deg}, {error_deg}")
    if (nominal_angles_deg is None) == (nominal_gravity is None):
        raise RegistrationError("give either nominal_angles_deg or nominal_gravity")
    nominal_of = nominal_angles_deg if nominal_gravity is None else nominal_gravity
    unknown = sorted(set(nominal_of) - set(gravity_ref_by_scan))
    if unknown:
        raise RegistrationError(f"nominal postures given for unknown scans: {unknown}")
    names = [s for s in gravity_ref_by_scan if s in nominal_of]
    checks = []
    for a, b in itertools.combinations(names, 2):
        measured = angle_between_deg(gravity_ref_by_scan[a], gravity_ref_by_scan[b])
        if nominal_gravity is None:
            nominal = _nominal_difference_deg(nominal_angles_deg[a], nominal_angles_deg[b])
        else:
            nominal = angle_between_deg(nominal_gravity[a], nominal_gravity[b])
        disc = abs(measured - nominal)
        status = "error" if disc > error_deg else "warn" if disc > warn_deg else "ok"
        checks.append(PostureCheck(a, b, measured, nominal, disc, status))
    bad = [c for c in checks if c.status == "error"]
    if bad:
        lines = "; ".join(_describe(c) for c in bad)
        raise PostureMismatchError(
            f"registered gravity contradicts the nominal postures by more than {error_deg} deg: "
            f"{lines}. Check the posture angles in session.toml and the fiducial detection."
        )
    for c in checks:
        if c.status == "warn":
            warnings.warn(
                f"posture mismatch above {warn_deg} deg: {_describe(c)}",
                PostureMismatchWarning,
                stacklevel=2,
            )
    for c in checks:
        log.debug("posture check %s", _describe(c))
    return checks


def _describe(c: PostureCheck) -> str:
    return (
        f"{c.scan_a} vs {c.scan_b}: gravity angle {c.measured_deg:.2f} deg, nominal "
        f"{c.nominal_deg:.2f} deg (off by {c.discrepancy_deg:.2f} deg)"
    )
