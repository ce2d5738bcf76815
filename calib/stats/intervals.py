"""Intervals of least-squares parameters under spatially correlated residual noise.

The calibration minimises ``sum r^2`` (ordinary least squares) over ``theta`` (p
parameters; ``theta = ln c1`` today); linearised, ``theta_hat - theta = A' eps`` with
``A = J (J'J)^{-1}`` and ``eps`` the noise, so ``Cov theta_hat = A' Sigma A``, the
sandwich ``(J'J)^{-1} J' Sigma J (J'J)^{-1}`` (White 1980; Freedman 2006 on its use).

Plug-in sandwich (:func:`sandwich_covariance`, ``method="sandwich"``). With ``Sigma``
from the fitted noise model this is exact if the model is. It is not: the variance of a
smooth weighted sum of the noise is set by its long-range correlation (the correlation
area, ``2 pi l^2``), which a short-range variogram of one realisation pins down poorly
(about a factor 2 at l = 20 mm on a 150 mm phantom), and a normal quantile then covers
88 % instead of 95 %.

Series estimator (default, ``method="series"``). For ``c' theta`` with influence vector
``a = A c``, the weighted residuals are looked at through ``K`` smooth modes
``v_k = (phi_k a)`` projected off the span of ``J`` and orthonormalised (``phi_k``:
polynomials of degree <= 2 in each scan's coordinates, :mod:`calib.stats.modes`). Each
``u_k = v_k' r = v_k' eps`` is, for noise correlated over less than the mode's scale,
another draw of the noise that ``a' eps`` is made of, so
``V = sum_k w_k u_k^2`` estimates ``Var(a' eps)`` from the data themselves (the
orthonormal-series long-run variance of Phillips 2005 and Sun 2013; spatially, Müller &
Watson 2022). The noise model only supplies the weights ``w_k = a'Sigma a / (K v_k'
Sigma v_k)`` (each term unbiased under the model: a small correction where a mode is not
smooth on the noise's scale) and the reference distribution of
``T = (c' theta_hat - c' theta) / sqrt(V)``: ``T`` is a ratio of Gaussian quadratic
forms in ``(a' eps, u)``, whose exact quantile under the model follows from Imhof's
formula (:mod:`calib.stats.quadform`), about ``t`` with ``nu ~ K`` degrees of freedom.
Errors in the fitted length now move the quantile a little instead of the variance a
lot. Where several kernels fit the variogram about equally well (``alternatives``), the
widest interval is reported.

Measured coverage of nominal 95 % (``python benchmarks/bench_coverage.py --table coverage
--draws 1000``; 20 cells: exponential and Gaussian kernels, l = 2-20 mm, nugget 0-0.3,
1 scan of 2000 or 3 scans of 1000 points, 1000 draws each, binomial se 0.6-0.8 %): series
with plausible alternatives 93.5-96.0 % in every cell, at a median width 1.03-1.18 times
the oracle's; plug-in sandwich with z 88.8-96.3 %; the formula of
``calib/fitting/uncertainty.py`` 29-98 % (its pairs join scans).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from .modes import orthonormalise, scan_polynomials
from .noise import NoiseArg, NoiseModel, apply_covariance, whitener
from .quadform import Quantile, ratio_critical_value, satterthwaite
from .sample import SurfaceSample

__all__ = [
    "MIN_SERIES_POINTS",
    "IntervalError",
    "ParameterInterval",
    "SeriesDesign",
    "SeriesStatistic",
    "gls_covariance",
    "parameter_intervals",
    "sandwich_covariance",
    "series_design",
    "series_interval",
    "series_statistic",
]

#: Fewest surface residuals for the variogram noise model and the series interval
#: (calibrate's; fewer, it takes the Gauss-Newton interval).
MIN_SERIES_POINTS = 200


class IntervalError(ValueError):
    """A Jacobian, contrast or residual that admits no interval."""


def _json_number(v):
    """Floats as float, non-finite as None; ints and strings unchanged."""
    if isinstance(v, (bool, str, int, np.integer)):
        return int(v) if isinstance(v, np.integer) else v
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    return v


@dataclass(frozen=True)
class ParameterInterval:
    """Interval of one linear combination ``c' theta`` of the fitted parameters.

    Attributes
    ----------
    estimate : float
        ``c' theta_hat`` (units of theta).
    standard_error : float
        ``sqrt(V)``: the series estimate (``method="series"``) or the plug-in sandwich.
    lower, upper : float
        The interval ``estimate -+ critical_value * standard_error``.
    level : float
    critical_value : float
    dof : float
        Satterthwaite degrees of freedom of ``V`` under the noise model (inf for the
        plug-in sandwich).
    n_modes : int
        ``K``, the smooth modes behind ``V`` (0 for the plug-in).
    method : str
        ``"series"`` or ``"sandwich"``.
    quantile : str
        ``"imhof"``, ``"satterthwaite"`` or ``"normal"``.
    noise : NoiseModel
        The model that gave the reported (widest) interval.
    plugin_standard_error : float
        ``sqrt(a' Sigma a)`` under that model, for comparison.
    """

    estimate: float
    standard_error: float
    lower: float
    upper: float
    level: float
    critical_value: float
    dof: float
    n_modes: int
    method: str
    quantile: str
    noise: NoiseModel
    plugin_standard_error: float

    def as_json(self) -> dict:
        """Plain JSON types (non-finite numbers as None), the noise model nested."""
        out = {k: _json_number(getattr(self, k)) for k in self.__dataclass_fields__}
        return out | {"noise": self.noise.as_json()}


@dataclass(frozen=True, eq=False)
class SeriesDesign:
    """Geometry-only part of a series interval: influence vector and smooth modes.

    Attributes
    ----------
    sample : SurfaceSample
    influence : ndarray, shape (n,)
        ``a = J (J'J)^{-1} c``: ``c' theta_hat - c' theta = a' eps`` (linearised).
    modes : ndarray, shape (n, K)
        ``v_k``, orthogonal to ``J`` and to each other, each of norm ``|a|``.
    mode_degree : ndarray of int, shape (K,)
        Polynomial degree behind each mode.
    """

    sample: SurfaceSample
    influence: np.ndarray
    modes: np.ndarray
    mode_degree: np.ndarray

    @property
    def columns(self) -> np.ndarray:
        """``[a, v_1..v_K]``, shape (n, K + 1)."""
        return np.column_stack([self.influence, self.modes])


def _jacobian(sample: SurfaceSample, jacobian: np.ndarray) -> np.ndarray:
    J = sample.check_values(jacobian, "jacobian", columns=True)
    s = np.linalg.svd(J, compute_uv=False)
    if not s[-1] > 1e-10 * max(s[0], 1e-300):
        raise IntervalError(
            f"the Jacobian (n={J.shape[0]}, p={J.shape[1]}) has rank < p (singular values "
            f"{s.round(6).tolist()}): some parameter does not change the residuals"
        )
    return J


def series_design(
    sample: SurfaceSample,
    jacobian: np.ndarray,
    *,
    contrast: np.ndarray | None = None,
    degree: int = 2,
) -> SeriesDesign:
    """Influence vector and smooth modes for the interval of ``c' theta``.

    Parameters
    ----------
    sample : SurfaceSample
    jacobian : ndarray, shape (n,) or (n, p)
        ``dr / dtheta`` (mm per unit of theta).
    contrast : ndarray, shape (p,), optional
        ``c``; default: the first parameter.
    degree : int
        Largest polynomial degree of the modes (per scan: ``C(degree + 3, 3)`` modes,
        less dependent ones and those ``J`` absorbs).

    Returns
    -------
    SeriesDesign
    """
    J = _jacobian(sample, jacobian)
    p = J.shape[1]
    c = np.eye(p)[0] if contrast is None else np.asarray(contrast, dtype=float).reshape(-1)
    if c.shape != (p,) or not np.any(c):
        raise IntervalError(f"contrast must be a non-zero vector of length {p}, got {c}")
    a = J @ np.linalg.solve(J.T @ J, c)
    phi, deg = scan_polynomials(sample, degree)
    v, kept = orthonormalise(phi * a[:, None], against=J)
    if v.shape[1] == 0:
        raise IntervalError("no smooth mode is left once J is projected out")
    return SeriesDesign(sample, a, v * np.linalg.norm(a), deg[kept])


def _omega(design: SeriesDesign, noise: NoiseArg) -> np.ndarray:
    cols = design.columns
    om = cols.T @ apply_covariance(design.sample, noise, cols)
    return 0.5 * (om + om.T)


@dataclass(frozen=True)
class SeriesStatistic:
    """The series variance of ``a' eps`` under one noise model, with its reference.

    Attributes
    ----------
    standard_error : float
        ``sqrt(V)``, ``V = sum_k w_k u_k^2`` over the kept modes.
    omega : ndarray, shape (K + 1, K + 1)
        Model covariance of ``(a' eps, u_1..u_K)`` over the kept modes.
    weights : ndarray, shape (K,)
    dof : float
        Satterthwaite degrees of freedom of ``V``.
    plugin_standard_error : float
        ``sqrt(a' Sigma a)``.
    noise : NoiseModel or mapping
    """

    standard_error: float
    omega: np.ndarray
    weights: np.ndarray
    dof: float
    plugin_standard_error: float
    noise: object

    @property
    def n_modes(self) -> int:
        """Modes kept."""
        return len(self.weights)


def series_statistic(
    design: SeriesDesign,
    residual_mm: np.ndarray,
    noise: NoiseArg,
    *,
    min_flatness: float = 0.1,
    omega: np.ndarray | None = None,
) -> SeriesStatistic:
    """Series variance of ``a' eps`` from the residual, weights and reference from a model.

    Parameters
    ----------
    design : SeriesDesign
    residual_mm : ndarray, shape (n,)
    noise : NoiseModel or mapping of scan label to NoiseModel
    min_flatness : float
        Modes whose model variance is below this fraction of ``a' Sigma a`` are left out.
    omega : ndarray, shape (K + 1, K + 1), optional
        ``C' Sigma C`` for ``C = design.columns`` under ``noise``, when already computed.

    Returns
    -------
    SeriesStatistic
    """
    r = design.sample.check_values(residual_mm, "residual_mm")
    u = design.modes.T @ r
    om = _omega(design, noise) if omega is None else omega
    flat = np.diag(om)[1:] / om[0, 0]  # 1 for every mode under white noise
    keep = np.flatnonzero(flat >= min_flatness)
    if keep.size == 0:
        keep = np.array([int(np.argmax(flat))])
    sub = om[np.ix_(np.r_[0, keep + 1], np.r_[0, keep + 1])]
    w = om[0, 0] / (len(keep) * np.diag(sub)[1:])  # each w_k u_k^2 unbiased for a'Sigma a
    var = float(np.sum(w * u[keep] ** 2))
    _, dof = satterthwaite(sub, w)
    return SeriesStatistic(float(np.sqrt(var)), sub, w, dof, float(np.sqrt(om[0, 0])), noise)


def _models(noise: NoiseArg, alternatives) -> list:
    return [noise, *alternatives]


def _shown(noise: NoiseArg) -> NoiseModel:
    """The model to report (the first scan's where models differ by scan)."""
    return noise if isinstance(noise, NoiseModel) else next(iter(noise.values()))


def series_interval(
    design: SeriesDesign,
    residual_mm: np.ndarray,
    noise: NoiseArg,
    *,
    estimate: float,
    level: float = 0.95,
    quantile: Quantile = "imhof",
    alternatives: tuple[NoiseArg, ...] = (),
    min_flatness: float = 0.1,
) -> ParameterInterval:
    """Series-variance interval of ``c' theta`` (see the module docstring).

    Parameters
    ----------
    design : SeriesDesign
        From :func:`series_design` (depends on the geometry and ``J`` only).
    residual_mm : ndarray, shape (n,)
        Residuals at the fit (orthogonal to ``J`` up to the optimiser's tolerance).
    noise : NoiseModel or mapping of scan label to NoiseModel
        The fitted noise model (short-range estimate).
    estimate : float
        ``c' theta_hat``.
    level : float
    quantile : {"imhof", "satterthwaite"}
    alternatives : tuple
        Other plausible noise models (:attr:`NoiseFit.plausible`); the widest interval
        is kept.
    min_flatness : float
        Modes whose variance under the model is below this fraction of
        ``a' Sigma a`` (not smooth on the noise's scale) are left out.

    Returns
    -------
    ParameterInterval
    """
    best = None
    for model in _models(noise, alternatives):
        st = series_statistic(design, residual_mm, model, min_flatness=min_flatness)
        cv = ratio_critical_value(st.omega, st.weights, level=level, method=quantile)
        if best is None or cv * st.standard_error > best[0] * best[1].standard_error:
            best = (cv, st)
    cv, st = best
    se = st.standard_error
    return ParameterInterval(float(estimate), se, float(estimate - cv * se),
                             float(estimate + cv * se), level, cv, st.dof, st.n_modes, "series",
                             quantile, _shown(st.noise), st.plugin_standard_error)  # fmt: skip


def sandwich_covariance(sample: SurfaceSample, jacobian: np.ndarray, noise: NoiseArg) -> np.ndarray:
    """Plug-in sandwich ``(J'J)^{-1} J' Sigma J (J'J)^{-1}`` of the OLS parameters.

    Parameters
    ----------
    sample : SurfaceSample
    jacobian : ndarray, shape (n,) or (n, p)
        ``dr / dtheta`` at the fit (mm per unit of theta).
    noise : NoiseModel or mapping of scan label to NoiseModel

    Returns
    -------
    ndarray, shape (p, p)
        In (units of theta)^2.

    Raises
    ------
    IntervalError
        The Jacobian has rank < p.
    SampleError
        ``jacobian`` has not one finite row per point of ``sample``.
    """
    J = _jacobian(sample, jacobian)
    bread = np.linalg.inv(J.T @ J)
    meat = J.T @ apply_covariance(sample, noise, J)  # Eq. (2), White 1980 (model meat)
    out = bread @ meat @ bread
    return 0.5 * (out + out.T)


def gls_covariance(sample: SurfaceSample, jacobian: np.ndarray, noise: NoiseArg) -> np.ndarray:
    """``(J' Sigma^{-1} J)^{-1}``: covariance of the GLS estimate under the model.

    Parameters
    ----------
    sample : SurfaceSample
        Every scan at most :data:`calib.stats.sample.MAX_DENSE_BLOCK` points.
    jacobian : ndarray, shape (n,) or (n, p)
    noise : NoiseModel or mapping of scan label to NoiseModel

    Returns
    -------
    ndarray, shape (p, p)
    """
    J = _jacobian(sample, jacobian)
    Jw = whitener(sample, noise).apply(J)
    return np.linalg.inv(Jw.T @ Jw)


def parameter_intervals(
    theta: np.ndarray,
    jacobian: np.ndarray,
    residual_mm: np.ndarray,
    sample: SurfaceSample,
    noise: NoiseArg,
    *,
    level: float = 0.95,
    method: Literal["series", "sandwich"] = "series",
    degree: int = 2,
    quantile: Quantile = "imhof",
    alternatives: tuple[NoiseArg, ...] = (),
) -> tuple[ParameterInterval, ...]:
    """Interval of every fitted parameter.

    Parameters
    ----------
    theta : ndarray, shape (p,)
        The fitted parameters (e.g. ``[ln c1]``).
    jacobian : ndarray, shape (n,) or (n, p)
        ``dr / dtheta`` at the fit (mm per unit of theta).
    residual_mm : ndarray, shape (n,)
        Residuals at the fit, mm.
    sample : SurfaceSample
    noise : NoiseModel or mapping of scan label to NoiseModel
    level : float
        Coverage of the interval, in (0, 1).
    method : {"series", "sandwich"}
        The series estimator with its exact reference (default) or the plug-in sandwich
        with a normal quantile (for comparison: it under-covers).
    degree, quantile, alternatives
        See :func:`series_design` and :func:`series_interval`.

    Returns
    -------
    tuple of ParameterInterval
        One per parameter, in order.

    Raises
    ------
    IntervalError
        ``theta``'s length differs from the Jacobian's column count, the Jacobian has
        rank < p, ``method`` is unknown, or no smooth mode is left once ``J`` is
        projected out.
    SampleError
        ``jacobian`` or ``residual_mm`` has not one finite row per point of ``sample``.
    """
    from scipy import stats

    th = np.atleast_1d(np.asarray(theta, dtype=float))
    J = _jacobian(sample, jacobian)
    if th.shape != (J.shape[1],):
        raise IntervalError(f"theta has shape {th.shape}; the Jacobian has {J.shape[1]} columns")
    out = []
    for k in range(len(th)):
        c = np.eye(len(th))[k]
        if method == "series":
            d = series_design(sample, J, contrast=c, degree=degree)
            out.append(series_interval(d, residual_mm, noise, estimate=float(th[k]), level=level,
                                       quantile=quantile, alternatives=alternatives))  # fmt: skip
            continue
        if method != "sandwich":
            raise IntervalError(f"method must be 'series' or 'sandwich', got {method!r}")
        z = float(stats.norm.ppf(0.5 + 0.5 * level))
        se = float(np.sqrt(sandwich_covariance(sample, J, noise)[k, k]))
        model = _shown(noise)
        out.append(ParameterInterval(float(th[k]), se, float(th[k] - z * se),
                                     float(th[k] + z * se), level, z, float("inf"), 0,
                                     "sandwich", "normal", model, se))  # fmt: skip
    return tuple(out)
