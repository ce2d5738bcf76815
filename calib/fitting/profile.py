"""Likelihood profiles over c1, and the ``nipple`` objective's 95 % interval from one.

:func:`likelihood_profile` evaluates the objective on a few values of c1 around the
optimum (reported in ``calibration.json``'s ``profile``).

The nipple objective has one residual per scan: the signed distance of the simulated
nipple to the measured surface. At the optimum the simulated nipple slides along the
measured surface near its tip, so the residual's derivative in c1 is close to zero and
the Gauss-Newton interval is useless (0 to infinity). The residual still grows
(quadratically) away from the optimum, and with a known noise level the likelihood
profile bounds c1 (:func:`calib.fitting.uncertainty.profile_ci95`).

The noise level is measured apart from the nipple residual: the root mean square of the
surface residuals (measured points to the simulated surface, fiducial frame) within
``radius_mm`` of each scan's measured nipple (or its 10th nearest point, see
:func:`nipple_patches`), at the calibrated c1. It holds the surface's
localisation noise and whatever the model misses near the nipple, so the interval is
conservative rather than optimistic.
"""

from __future__ import annotations

import logging

import numpy as np

from ..model.residuals import scan_residuals
from .uncertainty import ProfileInterval, Uncertainty, profile_ci95

__all__ = [
    "PATCH_RADIUS_MM",
    "likelihood_profile",
    "nipple_interval",
    "nipple_noise_sd_mm",
    "nipple_patches",
    "profile_rows",
]

log = logging.getLogger(__name__)
PATCH_RADIUS_MM = 15.0
MIN_PATCH_POINTS = 10
#: A patch with fewer points grows up to this factor of its radius, to its
#: ``MIN_PATCH_POINTS``-th nearest point: calibrate's subsample has a fixed count, so a
#: larger body has fewer points near its nipple (a 2.5 times larger twin dome: median 16
#: and at least 7 of 3000 within 15 mm over 20 seeds, against 103 at the twin's size).
PATCH_GROWTH = 2.0


def nipple_patches(cal, *, radius_mm: float = PATCH_RADIUS_MM) -> list:
    """Each calibration scan and its measured surface points near its nipple.

    Measured points only: the ``nipple`` objective checks them before its fit, so that a
    patch too small for the noise level stops the run before the optimisation.

    Parameters
    ----------
    cal : Calibrator
    radius_mm : float

    Returns
    -------
    list of (ScanMeasurement, ndarray of shape (k, 3))
        A patch with fewer than ``MIN_PATCH_POINTS`` points within ``radius_mm`` reaches
        its ``MIN_PATCH_POINTS``-th nearest point, up to ``PATCH_GROWTH`` times the radius.

    Raises
    ------
    ValueError
        A scan with fewer than ``MIN_PATCH_POINTS`` sampled points within
        ``PATCH_GROWTH * radius_mm``.
    """
    out = []
    for s in cal.calibration_scans:
        d = np.linalg.norm(cal.points[s.name] - s.nipple_mm, axis=1)
        r, n_in = radius_mm, int(np.count_nonzero(d < radius_mm))
        if n_in < MIN_PATCH_POINTS and len(d) >= MIN_PATCH_POINTS:
            reach = float(np.partition(d, MIN_PATCH_POINTS - 1)[MIN_PATCH_POINTS - 1])
            if reach < PATCH_GROWTH * radius_mm:
                r = np.nextafter(reach, np.inf)
                log.warning(
                    "scan %r: the nipple's noise patch reaches %.1f mm (%d subsampled points "
                    "within %g mm): its noise level takes in more of the model's misfit",
                    s.name,
                    r,
                    n_in,
                    radius_mm,
                )
        near = cal.points[s.name][d < r]
        if len(near) < MIN_PATCH_POINTS:
            raise ValueError(
                f"scan {s.name!r}: {n_in} measured surface points within {radius_mm} mm "
                f"of the nipple, {np.count_nonzero(d < PATCH_GROWTH * radius_mm)} within "
                f"{PATCH_GROWTH * radius_mm:g} mm (at least {MIN_PATCH_POINTS} needed for "
                "its noise level)"
            )
        out.append((s, near))
    return out


def nipple_noise_sd_mm(cal, *, radius_mm: float = PATCH_RADIUS_MM) -> float:
    """RMS surface residual (mm) near the measured nipples, at the current states.

    Parameters
    ----------
    cal : Calibrator
        After :meth:`Calibrator.residuals` at the calibrated c1 (its ``states``).
    radius_mm : float
        Patch radius around each calibration scan's measured nipple.
    """
    r = []
    for s, near in nipple_patches(cal, radius_mm=radius_mm):
        st = cal.states[s.name]
        res = scan_residuals("surface", s, cal.mesh, cal.sim, st.positions_mm, None,
                             surface_points_mm=near)  # fmt: skip
        r.append(res.r)
    return float(np.sqrt(np.mean(np.concatenate(r) ** 2)))


def nipple_interval(cal, theta: float, r_hat: np.ndarray) -> tuple[Uncertainty, ProfileInterval]:
    """Profile-likelihood 95 % interval of c1 for the nipple objective.

    Parameters
    ----------
    cal : Calibrator
        With its states at ``theta`` (the calibrated ``ln c1``).
    theta : float
    r_hat : ndarray, shape (n_scans,)
        The nipple residuals at ``theta``, mm.

    Returns
    -------
    Uncertainty
        ``method="profile"``; ``se_ln_c1`` is the interval's half width in ln c1 over
        1.96 (None when a side is open), ``residual_sd_mm`` the noise level used.
    ProfileInterval
        The evaluated profile.
    """
    sd = nipple_noise_sd_mm(cal)

    def sum_sq(t: float) -> float:
        res = cal.residuals(float(t), cal.calibration_scans, gradient=False)
        return float(sum(np.sum(v.r**2) for v in res.values()))

    prof = profile_ci95(sum_sq, theta, float(np.sum(r_hat**2)), sd)
    lo, hi = prof.ln_c1_bounds
    n = len(r_hat)
    interval = {
        "level": 0.95,
        "c1_bounds_pa": [None if b is None else float(np.exp(b)) for b in (lo, hi)],
        "open": list(prof.open_why),
    }
    if lo is None or hi is None:
        for side, why in zip(("lower bound open", "upper bound open"), prof.open_why, strict=True):
            if why is not None:
                log.warning("no 95 %% interval of c1 from the nipple error: %s (%s)", side, why)
        unc = Uncertainty(None, None, sd, n, float(n), 0.0, method="profile", interval=interval)
        return unc, prof
    se = (hi - lo) / (2.0 * 1.959963984540054)
    ci = (float(np.exp(lo)), float(np.exp(hi)))
    unc = Uncertainty(float(se), ci, sd, n, float(n), 0.0, method="profile", interval=interval)
    return unc, prof


def profile_rows(prof: ProfileInterval, n_residuals: int) -> list[dict]:
    """The evaluated profile as ``calibration.json`` rows (as the Gauss-Newton profile).

    A point whose FE solve failed is a row ``{"c1_pa", "objective": None, "failed": True}``.
    """
    rows = [
        {"c1_pa": float(np.exp(t)), "objective": 0.5 * s / n_residuals,
         "minus2_delta_loglik": float(dev)}
        for t, s, dev in prof.points
    ]  # fmt: skip
    failed = [
        {"c1_pa": float(np.exp(t)), "objective": None, "failed": True} for t in prof.failed_ln_c1
    ]
    return sorted(rows + failed, key=lambda row: row["c1_pa"])


def likelihood_profile(
    cal, theta: float, se: float | None, n_eff: float, *, say=None
) -> list[dict]:
    """The objective on ``profile_points`` values of ln c1 around ``theta`` (+-2 se).

    Each row has ``c1_pa``, ``objective`` and ``minus2_delta_loglik`` (``n_eff ln(J/J_min)``,
    the Gaussian profile with the noise level profiled out); a point whose FE solve fails
    is recorded with ``"failed": true``, not fatal. ``say`` (optional) is called with a
    line per point (review AX: a minute of FE solves passed without a word).
    """
    k = cal.options.profile_points
    if k < 2:
        return []
    half = max(2.0 * se, 0.05) if se is not None and np.isfinite(se) else 0.2
    rows = []
    for j, t in enumerate(np.linspace(theta - half, theta + half, k), start=1):
        rows.append(_profile_point(cal, float(t)))
        if say is not None:
            row = rows[-1]
            value = (
                "no FE solution" if row.get("failed") else f"objective {row['objective']:.4g} mm^2"
            )
            say(f"  profile point {j}/{k}: c1 = {row['c1_pa']:.1f} Pa, {value}")
    jmin = min((row["objective"] for row in rows if not row.get("failed")), default=None)
    for row in rows:
        if not row.get("failed"):
            row["minus2_delta_loglik"] = float(n_eff * np.log(row["objective"] / jmin))
    return rows


def _profile_point(cal, theta: float) -> dict:
    """One profile row; a point whose FE solve fails is recorded as failed, not fatal."""
    import fem

    try:
        res = cal.residuals(theta, cal.calibration_scans, gradient=False, retry=False)
    except fem.ConvergenceError as exc:
        log.warning("likelihood profile: FE failed at c1=%.1f Pa (%s)", np.exp(theta), exc)
        return {"c1_pa": float(np.exp(theta)), "objective": None, "failed": True}
    r = np.concatenate([v.r for v in res.values()])
    return {"c1_pa": float(np.exp(theta)), "objective": 0.5 * float(np.mean(r**2))}
