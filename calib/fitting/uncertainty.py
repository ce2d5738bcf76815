"""Uncertainty of the calibrated c1: Gauss-Newton with effective sample counts.

Surface residuals are spatially correlated, so the number of independent samples is
the measured area over the area of one correlation patch, not the vertex count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..stats.scores import MISFIT_ALPHA

__all__ = [
    "GAUSS_NEWTON_COVERAGE",
    "ProfileInterval",
    "Uncertainty",
    "correlation_length_mm",
    "gauss_newton_uncertainty",
    "profile_ci95",
]

#: What the Gauss-Newton interval covers on correlated noise, said wherever a surface fit
#: took it (README, the surface interval's measured coverage; ``python
#: benchmarks/bench_coverage.py --table coverage``).
GAUSS_NEWTON_COVERAGE = "on correlated noise it covered 29-98 % of a nominal 95 %"


def correlation_length_mm(points_mm: np.ndarray, r: np.ndarray, *, seed: int = 0) -> float:
    """Distance at which the residuals' spatial correlation falls below 1/e.

    Estimated from a seeded sample of point pairs binned by distance.
    """
    n = len(r)
    if n < 10 or np.std(r) == 0:
        return 0.0
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, 40000), rng.integers(0, n, 40000)
    d = np.linalg.norm(points_mm[i] - points_mm[j], axis=1)
    z = (r - r.mean()) / r.std()
    prod = z[i] * z[j]
    edges = np.linspace(0.0, np.percentile(d, 90), 31)
    idx = np.digitize(d, edges) - 1
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() >= 30 and prod[sel].mean() < np.exp(-1.0):
            return float(0.5 * (edges[b] + edges[b + 1]))
    return float(edges[-1])


@dataclass(frozen=True)
class Uncertainty:
    """Standard error and 95 % interval of c1.

    Attributes
    ----------
    se_ln_c1 : float or None
        Standard error of ln c1; None when the residuals leave no degree of freedom to
        estimate their noise (a single residual: the ``nipple`` objective) or do not
        change with c1 (then ``c1_ci95_pa`` is None too).
    c1_ci95_pa : tuple of float or None
    residual_sd_mm : float
        Residual noise estimate: the residuals' RMS about zero, sqrt(sum r^2 / (n - 1))
        (not about their mean; for ``profile`` the noise level the profile used).
    n_residuals : int
        Residual count.
    n_effective : float
        Effective independent samples.
    correlation_length_mm : float
        ``series``: the noise kernel's length scale; ``gauss-newton``: the distance at
        which the residuals' correlation falls below 1/e (0 when treated as independent).
    method : str
        ``series`` (the surface objective: :func:`series_uncertainty`), ``gauss-newton``
        (noise estimated from the residuals, effective sample count) or ``profile`` (the
        likelihood profile with a noise level measured apart: :func:`profile_ci95`).
    interval : dict or None
        ``series``: :meth:`calib.stats.ParameterInterval.as_json` of ln c1 (standard error,
        critical value, degrees of freedom, the noise model behind it); ``gauss-newton``:
        ``distribution`` (student t), ``standard_error``, ``critical_value`` and
        ``degrees_of_freedom``.
    """

    se_ln_c1: float | None
    c1_ci95_pa: tuple[float, float] | None
    residual_sd_mm: float
    n_residuals: int
    n_effective: float
    correlation_length_mm: float
    method: str = "gauss-newton"
    interval: dict | None = None


def gauss_newton_uncertainty(
    c1_pa: float, r: np.ndarray, dr: np.ndarray, points_mm: np.ndarray, *, area_mm2: float | None
) -> Uncertainty:
    """Gauss-Newton standard error of ln c1, inflated by ``n / n_eff``, and its t interval.

    The 95 % interval takes Student's t quantile on ``n_eff - 1`` degrees of freedom (the
    noise's sd is estimated from the same residuals); ``interval`` records it.

    Parameters
    ----------
    c1_pa : float
    r, dr : ndarray, shape (n,)
        Residuals (mm) and their derivatives in ln c1.
    points_mm : ndarray, shape (n, 3)
        Where the residuals live (correlation length).
    area_mm2 : float or None
        Measured area the residuals cover; None treats the residuals as independent.
    """
    from scipy import stats

    n = len(r)
    if n < 2:  # one residual and one parameter: no degree of freedom left for the noise
        return Uncertainty(None, None, float(np.abs(r).sum()), n, float(n), 0.0)
    sd = float(np.sqrt(np.sum(r**2) / (n - 1)))
    ell = correlation_length_mm(points_mm, r) if area_mm2 else 0.0
    n_eff = (
        float(n) if not area_mm2 or ell == 0 else float(np.clip(area_mm2 / (np.pi * ell**2), 2, n))
    )
    info = float(np.sum(dr**2))
    if not info > 0:  # the residuals do not change with c1: the data do not bound it
        return Uncertainty(None, None, sd, n, n_eff, ell)
    se = sd / np.sqrt(info) * np.sqrt(n / n_eff)
    # Student's t on the effective count less the fitted parameter: with few residuals
    # (the landmarks of one or two scans) the normal 1.96 covered 81-92 % of nominal 95 %
    dof = max(n_eff - 1.0, 1.0)
    crit = float(stats.t.ppf(0.975, dof))
    ci = (c1_pa * float(np.exp(-crit * se)), c1_pa * float(np.exp(crit * se)))
    interval = {
        "distribution": "student t",
        "standard_error": float(se),
        "critical_value": crit,
        "degrees_of_freedom": float(dof),
    }
    return Uncertainty(float(se), ci, sd, n, n_eff, ell, interval=interval)


def series_uncertainty(
    c1_pa: float,
    r: np.ndarray,
    dr: np.ndarray,
    points_mm: np.ndarray,
    scan_labels: np.ndarray,
    *,
    seed: int = 0,
    misfit_alpha: float = MISFIT_ALPHA,
    max_lag_mm: float | None = None,
):
    """Interval of ln c1 under a spatially correlated noise model, and the misfit test.

    The residuals' short-range variogram gives the noise model
    (:func:`calib.stats.estimate_noise`, pooled over the calibration scans, pairs within
    a scan, up to ``max_lag_mm``); the interval is the series-variance estimator with its
    exact (Imhof) reference distribution, the widest over the plausible kernels
    (:func:`calib.stats.parameter_intervals`; measured coverage 93.5-96.0 % of nominal
    95 % in 20 cells, ``python benchmarks/bench_coverage.py``). The band-F misfit test
    (:func:`calib.stats.misfit_test`) asks whether the residual holds large-scale
    structure the noise cannot explain: a misfit means the interval, which covers noise
    (and, added by the caller, the mesh), does not cover the model's own error.

    Parameters
    ----------
    c1_pa : float
    r, dr : ndarray, shape (n,)
        Residuals (mm) and their derivatives in ln c1 at the fit.
    points_mm : ndarray, shape (n, 3)
    scan_labels : ndarray of int, shape (n,)
        The scan of each residual.
    seed : int
        Seed of the variogram's pair sample.
    misfit_alpha : float
        False-alarm rate of the misfit test.
    max_lag_mm : float, optional
        The variogram's reach (mm); None: :data:`calib.stats.noise.MAX_LAG_MM`, sized
        for a twin-tall body (the calibration passes it times
        :func:`calib.model.reference.body_scale`).

    Returns
    -------
    uncertainty : Uncertainty
    model_fit : calib.stats.ModelFit
    """
    from ..stats import SurfaceSample, estimate_noise, misfit_test, parameter_intervals

    base = gauss_newton_uncertainty(c1_pa, r, dr, points_mm, area_mm2=None)
    sample = SurfaceSample(points_mm, np.asarray(scan_labels, dtype=np.int64))
    if max_lag_mm is None:
        from ..stats.noise import MAX_LAG_MM as max_lag_mm
    noise = estimate_noise(sample, r, seed=seed, max_lag_mm=max_lag_mm)
    alt = tuple(noise.plausible[1:])
    theta = float(np.log(c1_pa))
    (iv,) = parameter_intervals([theta], dr, r, sample, noise.best, alternatives=alt)
    fit = misfit_test(r, dr, sample, noise.best, alpha=misfit_alpha, alternatives=alt)
    # the count of independent residuals that would give this standard error (for the
    # likelihood profile's scaling): se_independent^2 / se^2 = n_eff / n
    ratio = (base.se_ln_c1 / iv.standard_error) ** 2 if iv.standard_error > 0 else 1.0
    unc = Uncertainty(
        se_ln_c1=float(iv.standard_error),
        c1_ci95_pa=(float(np.exp(iv.lower)), float(np.exp(iv.upper))),
        residual_sd_mm=base.residual_sd_mm,
        n_residuals=len(r),
        n_effective=float(np.clip(ratio * len(r), 2, len(r))),
        correlation_length_mm=float(iv.noise.length_mm),
        method="series",
        interval=iv.as_json(),
    )
    return unc, fit


CHI2_1_95 = 3.841458820694124  # 95 % quantile of chi-square with one degree of freedom


@dataclass(frozen=True)
class ProfileInterval:
    """Result of :func:`profile_ci95`.

    Attributes
    ----------
    ln_c1_bounds : tuple of (float or None)
        Lower and upper 95 % bounds of ln c1; None where the interval reaches past the
        search limit (the data do not bound c1 on that side).
    evaluations : int
        Objective evaluations (FE solves of every calibration scan) spent.
    points : tuple of (float, float, float)
        Every ``(ln c1, S in mm^2, -2 delta log-likelihood)`` evaluated, by ln c1.
    failed_ln_c1 : tuple of float
        Every ln c1 whose FE solve failed, in the order tried.
    open_why : tuple of (str or None)
        Why the lower and upper bounds are open (None where found): the search limit
        reached, or the FE solve that failed and ended the search on that side.
    """

    ln_c1_bounds: tuple[float | None, float | None]
    evaluations: int
    points: tuple[tuple[float, float, float], ...]
    failed_ln_c1: tuple[float, ...] = ()
    open_why: tuple[str | None, str | None] = (None, None)


def profile_ci95(
    sum_sq,
    theta_hat: float,
    sum_sq_min: float,
    noise_sd_mm: float,
    *,
    first_step: float = 0.05,
    limit: float = float(np.log(4.0)),
    tol: float = 0.005,
) -> ProfileInterval:
    """95 % likelihood-profile interval of ``theta = ln c1`` for residuals of known noise.

    With Gaussian residual noise of standard deviation ``s``,
    ``-2 delta log L(theta) = (S(theta) - S_min) / s**2`` with ``S`` the residuals' sum of
    squares; the bounds are where it reaches the chi-square(1) 95 % quantile, 3.84. Unlike
    the Gauss-Newton interval this needs no non-zero derivative at the optimum (the
    nipple's distance to the measured surface is flat there). Each side is bracketed by
    doubling steps from ``theta_hat``, then refined by false position on
    ``sqrt(-2 delta log L)`` to ``tol``.

    Parameters
    ----------
    sum_sq : callable
        ``sum_sq(theta) -> S`` in mm^2; may raise ``fem.ConvergenceError``, which ends
        the search on that side (the bound is then reported as open, and why).
    theta_hat, sum_sq_min : float
        The optimum and ``S`` there.
    noise_sd_mm : float
        Standard deviation of one residual, mm (> 0).
    first_step, limit, tol : float
        First step, largest distance searched and bound tolerance, all in ln c1.

    Returns
    -------
    ProfileInterval
    """
    from fem import ConvergenceError

    if not noise_sd_mm > 0:
        raise ValueError(f"the noise standard deviation must be positive, got {noise_sd_mm}")
    points: list[tuple[float, float, float]] = []
    failed: list[float] = []

    def root(t: float) -> float:  # sqrt(-2 dlogL) - sqrt(3.84) at offset t
        try:
            s = float(sum_sq(theta_hat + t))
        except ConvergenceError:
            failed.append(theta_hat + t)
            return np.inf
        dev = max(s - sum_sq_min, 0.0) / noise_sd_mm**2
        points.append((theta_hat + t, s, dev))
        return float(np.sqrt(dev) - np.sqrt(CHI2_1_95))

    bounds, why = [], []
    for side in (-1.0, 1.0):
        b, stopped = _bound(root, side, first_step, limit, tol)
        bounds.append(None if b is None else theta_hat + b)
        if b is not None:
            why.append(None)
        elif stopped is None:
            why.append(f"the data do not bound c1 within a factor {np.exp(limit):.3g}")
        else:  # review AJ: a failed solve was reported as data that do not bound c1
            why.append(f"no FE solution at c1 = {np.exp(theta_hat + stopped):.1f} Pa")
    return ProfileInterval(
        (bounds[0], bounds[1]), len(points), tuple(sorted(points)), tuple(failed), tuple(why)
    )


def _bound(root, side: float, step: float, limit: float, tol: float):
    """Signed offset where ``root`` crosses zero on one side, and where a solve failed.

    Returns ``(offset, None)``; ``(None, None)`` past ``limit``; ``(None, b)`` where the
    solve at offset ``b`` failed before the profile crossed (the search cannot go on).
    """
    a, fa, b = 0.0, -np.sqrt(CHI2_1_95), side * step
    fb = root(b)
    while fb < 0:
        if abs(b) >= limit:
            return None, None
        a, fa, b = b, fb, side * min(2.0 * abs(b), limit)
        fb = root(b)
    if not np.isfinite(fb):
        return None, b
    return _false_position(root, a, fa, b, fb, tol), None


def _false_position(root, a, fa, b, fb, tol: float) -> float:
    """Illinois false position for the root in ``[a, b]`` (``fa < 0 <= fb``).

    A failed evaluation inside the bracket (``root`` not finite) says nothing of the side
    the root lies on: the known outside end ``b`` is returned (the wider, conservative
    bound) instead of taking the failed point for an outside one.
    """
    keep = 0
    while abs(b - a) > tol:
        c = b - fb * (b - a) / (fb - fa)
        fc = root(c)
        if not np.isfinite(fc):
            return b
        if fc >= 0:
            b, fb = c, fc
            fa, keep = (fa / 2.0 if keep == 1 else fa), 1
        else:
            a, fa = c, fc
            fb, keep = (fb / 2.0 if keep == -1 else fb), -1
        if np.isfinite(fc) and abs(fc) < 1e-3:
            return c
    return 0.5 * (a + b)
