"""The residual noise model, estimated from the residuals' own variogram.

Within each scan, the empirical semivariogram of the residuals (Matheron's estimator,
Cressie 1993 Eq. 2.4.2) is binned by 3-D pair distance up to ``max_lag_mm``. Nugget +
partial sill + range of an exponential, Gaussian and Matérn 3/2 kernel
(:mod:`calib.stats.kernels`) are fitted by Cressie's (1985) weighted least squares
(weights ``N(h) / gamma(h)^2``, Cressie 1993 Eq. 2.6.12) and the kernel with the
smallest weighted criterion is chosen (all three have three parameters, so no penalty
is needed). The result is a frozen :class:`NoiseModel`.

Short range, not detrending. A residual that contains large-scale model misfit has a
variogram that keeps rising with the lag; fitting it to all lags would take the misfit
for long-range noise. Two remedies: fit only up to a cutoff (``max_lag_mm``, default
40 mm, the short-range estimate) or remove a smooth per-scan trend first
(``detrend="linear"|"quadratic"``). Detrending also removes the low-frequency part of
correlated noise, which is exactly what the variance of a smooth parameter (and the
misfit test's reference) depends on, so it biases the model towards white noise; a
smooth misfit adds only about ``|grad m|^2 h^2 / 2`` to the variogram at short lags. The
interval and the tests therefore use the short-range estimate without detrending
(``benchmarks/bench_coverage.py --table variogram`` measures both).

Covariances are block-diagonal by scan. :class:`Whitener` holds per-scan Cholesky
factors (dense, up to :data:`calib.stats.sample.MAX_DENSE_BLOCK` points per scan). Beyond
that, :func:`local_counts` gives the local effective-sample approximation
``x' Sigma^{-1} y ~ sum x_i y_i / (sigma^2 m_i)`` with ``m_i = sum_j R_ij``: exact for
fields that are constant over a correlation length, and what the package uses when a
scan is too large to factorise.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from .kernels import KERNELS, Kernel, correlation
from .modes import project_out, scan_polynomials
from .sample import MAX_DENSE_BLOCK, MAX_PAIRS, SurfaceSample

__all__ = [
    "MAX_LAG_MM",
    "N_BINS",
    "NoiseFit",
    "NoiseModel",
    "NoiseModelError",
    "Variogram",
    "SMOOTH_TAKEN_FOR_NOISE",
    "Whitener",
    "apply_covariance",
    "covariance_matrix",
    "effective_sample_count",
    "empirical_variogram",
    "estimate_noise",
    "fit_variogram",
    "local_counts",
    "session_noise",
    "whitener",
    "with_sigma",
]

Detrend = Literal["none", "linear", "quadratic"]
CHUNK = 2048  # rows per block when a covariance is applied without a dense matrix
#: The variogram's reach (mm, the short-range cutoff) and its equal-width bins: the
#: calibration's noise model and diagnose's tests (for the twins' 75 mm tall body:
#: :data:`calib.discrepancy.diagnose.NOISE_LAG_MM`).
MAX_LAG_MM = 40.0
N_BINS = 20
#: What a correlation length at its bound, or past the variogram's reach, means for a
#: misfit test under the noise model: one clause, said by calibrate and diagnose alike.
SMOOTH_TAKEN_FOR_NOISE = (
    "smooth structure was taken for noise, so the misfit test cannot tell a smooth "
    "misfit from noise here"
)


class NoiseModelError(ValueError):
    """A variogram or noise model that cannot be estimated or used."""


@dataclass(frozen=True)
class Variogram:
    """An empirical semivariogram, pooled over scans (pairs within scans only).

    Attributes
    ----------
    lag_mm : ndarray, shape (b,)
        Mean pair distance in each kept bin (mm).
    gamma_mm2 : ndarray, shape (b,)
        Semivariance ``mean((r_i - r_j)^2) / 2`` of the bin (mm^2).
    n_pairs : ndarray of int, shape (b,)
    variance_mm2 : float
        Variance of the (detrended) residuals about each scan's mean, for reference.
    max_lag_mm : float
    detrend : str
    thinned : bool
        Whether the pairs were subsampled (seeded).
    seed : int
    """

    lag_mm: np.ndarray
    gamma_mm2: np.ndarray
    n_pairs: np.ndarray
    variance_mm2: float
    max_lag_mm: float
    detrend: str
    thinned: bool
    seed: int


@dataclass(frozen=True)
class NoiseModel:
    """Stationary noise within a scan: ``sigma^2 ((1 - f) rho(h / l) + f [h = 0])``.

    Attributes
    ----------
    kernel : {"exponential", "gaussian", "matern32"}
    sigma_mm : float
        Standard deviation of one residual (nugget + partial sill), mm.
    nugget_fraction : float
        ``f``: share of the variance that is uncorrelated between points, in [0, 1].
    length_mm : float
        Kernel length scale ``l`` (mm); 0 for white noise.
    criterion : float
        Cressie's weighted criterion ``sum N (gamma_hat / gamma - 1)^2`` of the fit (nan
        for a model given by hand).
    n_pairs : int
        Pairs behind the fit.
    max_lag_mm : float
        Largest lag fitted.
    detrend : {"none", "linear", "quadratic"}
        Per-scan polynomial trend removed before the fit.
    length_at_bound : bool
        The fitted length reached the top of its search range: the variogram does not
        level off within ``max_lag_mm`` (long-range structure or misfit; see
        :func:`calib.stats.scores.misfit_test`).
    """

    kernel: Kernel
    sigma_mm: float
    nugget_fraction: float
    length_mm: float
    criterion: float = float("nan")
    n_pairs: int = 0
    max_lag_mm: float = float("nan")
    detrend: Detrend = "none"
    length_at_bound: bool = False

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise NoiseModelError(f"unknown kernel {self.kernel!r}; expected one of {KERNELS}")
        if not (self.sigma_mm > 0 and np.isfinite(self.sigma_mm)):
            raise NoiseModelError(f"sigma_mm must be positive and finite, got {self.sigma_mm}")
        if not 0.0 <= self.nugget_fraction <= 1.0:
            raise NoiseModelError(f"nugget_fraction must lie in [0, 1], got {self.nugget_fraction}")
        if not (self.length_mm >= 0 and np.isfinite(self.length_mm)):
            raise NoiseModelError(f"length_mm must be >= 0 and finite, got {self.length_mm}")

    def correlation(self, distance_mm: np.ndarray, *, same_points: bool = False) -> np.ndarray:
        """Correlation at the given distances (mm); the nugget on coincident points only.

        Parameters
        ----------
        distance_mm : ndarray, any shape; (n, n) when ``same_points``
            Distances between points, mm.
        same_points : bool
            ``distance_mm`` is the square distance matrix of one point set: the nugget
            goes on its diagonal. Otherwise only zero distances get it.

        Returns
        -------
        ndarray, shape like ``distance_mm``
            Correlation (dimensionless, in [0, 1]).
        """
        d = np.asarray(distance_mm, dtype=float)
        if same_points and self.white:  # independent, even where points coincide
            return np.eye(len(d))
        rho = correlation(self.kernel, d, self.length_mm)
        if self.nugget_fraction > 0:
            rho *= 1.0 - self.nugget_fraction
        if same_points:
            rho[np.diag_indices_from(rho)] += self.nugget_fraction
        elif self.nugget_fraction > 0:
            rho += self.nugget_fraction * (d == 0.0)
        return rho

    def covariance(self, points_mm: np.ndarray) -> np.ndarray:
        """Covariance matrix (mm^2) of the noise at points of one scan.

        Parameters
        ----------
        points_mm : ndarray, shape (n, 3)

        Returns
        -------
        ndarray, shape (n, n)
            For several scans use :func:`covariance_matrix` (zero between scans).

        Raises
        ------
        NoiseModelError
            ``points_mm`` is not an (n, 3) array.
        """
        from scipy.spatial.distance import cdist

        p = np.asarray(points_mm, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise NoiseModelError(f"points_mm must have shape (n, 3), got {p.shape}")
        return self.sigma_mm**2 * self.correlation(cdist(p, p), same_points=True)

    @property
    def white(self) -> bool:
        """No correlation between distinct points (length 0 or all nugget)."""
        return self.length_mm == 0.0 or self.nugget_fraction == 1.0

    def semivariance_mm2(self, lag_mm: np.ndarray) -> np.ndarray:
        """Model semivariogram ``gamma(h)`` for ``h > 0`` (mm^2).

        Parameters
        ----------
        lag_mm : ndarray, any shape
            Lags ``h`` between points, mm.

        Returns
        -------
        ndarray, shape like ``lag_mm``
            Semivariance, mm^2.
        """
        rho = correlation(self.kernel, np.asarray(lag_mm, dtype=float), self.length_mm)
        return self.sigma_mm**2 * (1.0 - (1.0 - self.nugget_fraction) * rho)

    def as_json(self) -> dict:
        """The model as plain JSON types (for ``calibration.json``; nan as None)."""
        return {
            "kernel": self.kernel,
            "sigma_mm": float(self.sigma_mm),
            "nugget_fraction": float(self.nugget_fraction),
            "length_mm": float(self.length_mm),
            "criterion": _finite_or_none(self.criterion),
            "n_pairs": int(self.n_pairs),
            "max_lag_mm": _finite_or_none(self.max_lag_mm),
            "detrend": self.detrend,
            "length_at_bound": bool(self.length_at_bound),
        }


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


@dataclass(frozen=True)
class NoiseFit:
    """Result of :func:`fit_variogram`: the chosen model and every kernel's fit.

    Attributes
    ----------
    best : NoiseModel
        The kernel with the smallest criterion.
    candidates : tuple of NoiseModel
        One fit per kernel tried, in the order given.
    plausible : tuple of NoiseModel
        Candidates whose criterion is within ``plausible_ratio`` of the best (the best
        first); intervals and tests take the most conservative of these.
    variogram : Variogram
    scan_sd_mm : mapping of int to float, optional
        Per scan label, its noise level in this fit's terms: the fit's sd times the
        square root of the scan's semivariance over the fit's scan's at the shortest lags
        (:func:`session_noise`; None for a fit of its own).
    scan_fits : mapping of int to NoiseModel, optional
        Each scan's own best fit (:func:`session_noise`): with :attr:`by_scan`, one more
        alternative (a scan imaged unlike may be correlated unlike too).
    reference_scan : int, optional
        The scan label this fit is of (:func:`session_noise`).
    by_scan : bool
        The scans are imaged unlike (the caller's judgement, :func:`session_noise`): the
        models :meth:`scaled` gives are one per scan, each at its scan's level.
    """

    best: NoiseModel
    candidates: tuple[NoiseModel, ...]
    plausible: tuple[NoiseModel, ...]
    variogram: Variogram
    scan_sd_mm: Mapping[int, float] | None = None
    scan_fits: Mapping[int, NoiseModel] | None = None
    reference_scan: int | None = None
    by_scan: bool = False

    def scaled(self, model: NoiseModel) -> NoiseArg:
        """``model`` for every scan, or one per scan at its level (:attr:`by_scan`).

        Parameters
        ----------
        model : NoiseModel
            :attr:`best` or one of :attr:`plausible`.

        Returns
        -------
        NoiseModel or dict of int to NoiseModel
            Where :attr:`by_scan`, scan ``k``'s model is ``model`` with its sd times
            ``scan_sd_mm[k] / scan_sd_mm[reference_scan]``.
        """
        if not self.by_scan:
            return model
        ref = self.scan_sd_mm[self.reference_scan]
        return {k: with_sigma(model, model.sigma_mm * v / ref) for k, v in self.scan_sd_mm.items()}

    @property
    def best_arg(self) -> NoiseArg:
        """:meth:`scaled` of :attr:`best`: what diagnose's tests, maps and floor use."""
        return self.scaled(self.best)

    @property
    def alternatives(self) -> tuple[NoiseArg, ...]:
        """:meth:`scaled` of the other plausible models (the tests' ``alternatives``).

        With :attr:`by_scan`, each scan's own fit too (the tests and intervals take the
        most conservative): thicker slices correlate the noise farther, and a noisier
        scan 9 mm correlated against 3 screened its own columns significant on null
        residuals in 32 % of draws at the quietest's correlation (review X).
        """
        scaled = tuple(self.scaled(m) for m in self.plausible[1:])
        if self.by_scan and self.scan_fits:
            return (*scaled, dict(self.scan_fits))
        return scaled

    def variance_mm2(self, sample: SurfaceSample) -> float:
        """The best model's noise variance, averaged over ``sample``'s points (mm^2).

        Parameters
        ----------
        sample : SurfaceSample
            Points and scan labels; with one model per scan, each scan weighs by its count.

        Returns
        -------
        float
            Variance, mm^2.

        Raises
        ------
        NoiseModelError
            The per-scan models lack one of ``sample``'s scan labels.
        """
        arg = self.best_arg
        if isinstance(arg, NoiseModel):
            return float(arg.sigma_mm**2)
        n = np.array([len(idx) for idx in sample.blocks], float)
        var = np.array([_model_for(arg, k).sigma_mm ** 2 for k in sample.labels])
        return float(n @ var / n.sum())


NoiseArg = NoiseModel | Mapping[int, NoiseModel]


def _model_for(noise: NoiseArg, label: int) -> NoiseModel:
    if isinstance(noise, NoiseModel):
        return noise
    try:
        return noise[label]
    except KeyError:
        raise NoiseModelError(f"no noise model for scan {label} (have {sorted(noise)})") from None


# ---------------------------------------------------------------------------- variogram


def _detrended(sample: SurfaceSample, r: np.ndarray, detrend: Detrend) -> np.ndarray:
    """Residuals minus a per-scan mean, plane or quadric (least squares)."""
    degree = {"none": 0, "linear": 1, "quadratic": 2}.get(detrend)
    if degree is None:
        raise NoiseModelError(f"detrend must be 'none', 'linear' or 'quadratic', got {detrend!r}")
    basis, _ = scan_polynomials(sample, degree)
    return project_out(basis, r)


def empirical_variogram(
    sample: SurfaceSample,
    residual_mm: np.ndarray,
    *,
    max_lag_mm: float = MAX_LAG_MM,
    n_bins: int = N_BINS,
    max_pairs: int = MAX_PAIRS,
    min_pairs: int = 30,
    detrend: Detrend = "none",
    seed: int = 0,
) -> Variogram:
    """Matheron's semivariogram of the residuals, pairs within scans, binned by distance.

    Parameters
    ----------
    sample : SurfaceSample
        Points (mm) and scan labels.
    residual_mm : ndarray, shape (n,)
    max_lag_mm : float
        Largest pair distance (mm): the short-range cutoff.
    n_bins : int
        Equal-width bins on ``(0, max_lag_mm]``.
    max_pairs : int
        Pairs are all those closer than ``max_lag_mm``, seeded-subsampled to this many.
    min_pairs : int
        Bins with fewer pairs are dropped.
    detrend : {"none", "linear", "quadratic"}
        Per-scan polynomial trend removed first (see the module docstring).
    seed : int

    Returns
    -------
    Variogram
    """
    r = sample.check_values(residual_mm, "residual_mm")
    if n_bins < 3:
        raise NoiseModelError(f"n_bins must be >= 3, got {n_bins}")
    r = _detrended(sample, r, detrend)
    pairs = sample.pairs(max_lag_mm, max_pairs=max_pairs, seed=seed)
    b, count, lag = pairs.bins(n_bins)
    half_sq = 0.5 * (r[pairs.i] - r[pairs.j]) ** 2  # Eq. (2.4.2), Cressie 1993
    gamma = np.bincount(b, weights=half_sq, minlength=n_bins) / np.maximum(count, 1)
    keep = count >= min_pairs
    if keep.sum() < 3:
        raise NoiseModelError(
            f"only {int(keep.sum())} distance bins with >= {min_pairs} pairs within "
            f"{max_lag_mm} mm ({len(pairs.i)} pairs in all): too few points per scan"
        )
    var = float(np.mean([np.var(r[idx]) for idx in sample.blocks if len(idx) > 1] or [0.0]))
    return Variogram(lag[keep], gamma[keep], count[keep].astype(np.int64), var,
                     float(max_lag_mm), detrend, pairs.thinned, int(seed))  # fmt: skip


# --------------------------------------------------------------------------- fitting


def _wls_two(g: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Non-negative weighted LS of ``y ~ c0 + c1 g`` for each row of ``g`` (shape (m, b)).

    Returns ``c0, c1`` (shape (m,)) minimising ``sum w (c0 + c1 g - y)^2`` with
    ``c0, c1 >= 0`` (the nugget and partial sill); closed form on each active set.
    """
    s0, s1, s2 = w.sum(), g @ w, (g * g) @ w
    t0, t1 = w @ y, (g * y) @ w
    det = s0 * s2 - s1 * s1
    with np.errstate(divide="ignore", invalid="ignore"):
        c0 = np.where(det > 0, (s2 * t0 - s1 * t1) / det, -1.0)
        c1 = np.where(det > 0, (s0 * t1 - s1 * t0) / det, -1.0)
        only1 = np.where(s2 > 0, np.maximum(t1 / s2, 0.0), 0.0)  # nugget 0
    only0 = max(t0 / s0, 0.0)  # partial sill 0

    def sse(a0, a1):
        return ((a0[:, None] + a1[:, None] * g - y) ** 2) @ w

    bad = (c0 < 0) | (c1 < 0)
    if bad.any():
        z = np.zeros_like(c1)
        e1, e0 = sse(z, only1), sse(np.full_like(c1, only0), z)
        use1 = e1 <= e0
        c0 = np.where(bad, np.where(use1, 0.0, only0), c0)
        c1 = np.where(bad, np.where(use1, only1, 0.0), c1)
    return c0, c1


def _fit_kernel(vg: Variogram, kernel: Kernel, n_grid: int) -> NoiseModel:
    """Nugget, partial sill and length of one kernel: profile WLS over log-spaced lengths.

    For each length on a log grid the nugget and partial sill follow in closed form
    (non-negative weighted LS); pass 1 weights with the empirical variogram, pass 2 with
    pass 1's model (Cressie 1985, iterated once); the best grid length is refined by a
    bounded scalar search in ``log l``.
    """
    from scipy.optimize import minimize_scalar

    h, y, n = vg.lag_mm, vg.gamma_mm2, vg.n_pairs.astype(float)
    lo = max(0.05 * float(h[0]), 1e-3)
    hi = 10.0 * vg.max_lag_mm
    grid = np.geomspace(lo, hi, n_grid)
    floor = 1e-9 * float(np.max(y))
    w = n / np.maximum(y, floor) ** 2
    best = None
    for _ in range(2):
        g = 1.0 - correlation(kernel, h[None, :] / grid[:, None], 1.0)
        c0, c1 = _wls_two(g, y, w)
        crit = ((c0[:, None] + c1[:, None] * g - y) ** 2) @ w
        k = int(np.argmin(crit))
        best = (grid[k], c0[k], c1[k])
        model = c0[k] + c1[k] * g[k]
        w = n / np.maximum(model, floor) ** 2  # Eq. (2.6.12), Cressie 1993

    def objective(log_l: float) -> float:
        gg = 1.0 - correlation(kernel, h[None, :] / np.exp(log_l), 1.0)
        a0, a1 = _wls_two(gg, y, w)
        return float((((a0[:, None] + a1[:, None] * gg - y) ** 2) @ w)[0])

    k = int(np.argmin(np.abs(grid - best[0])))
    a, b = np.log(grid[max(k - 1, 0)]), np.log(grid[min(k + 1, n_grid - 1)])
    res = minimize_scalar(objective, bounds=(a, b), method="bounded", options={"xatol": 1e-4})
    ell = float(np.exp(res.x)) if res.fun <= objective(np.log(best[0])) else float(best[0])
    g = 1.0 - correlation(kernel, h[None, :] / ell, 1.0)
    c0, c1 = (float(v[0]) for v in _wls_two(g, y, w))
    sill = c0 + c1
    if not sill > 0:
        raise NoiseModelError("the variogram is zero: the residuals are constant within scans")
    model = np.maximum(c0 + c1 * g[0], floor)
    crit = float(np.sum(n * (y / model - 1.0) ** 2))  # Cressie 1985 criterion
    white = c1 <= 1e-12 * sill
    return NoiseModel(
        kernel=kernel,
        sigma_mm=float(np.sqrt(sill)),
        nugget_fraction=1.0 if white else float(c0 / sill),
        length_mm=0.0 if white else ell,
        criterion=crit,
        n_pairs=int(vg.n_pairs.sum()),
        max_lag_mm=vg.max_lag_mm,
        detrend=vg.detrend,
        length_at_bound=bool(not white and ell >= 0.999 * hi),
    )


def fit_variogram(
    vg: Variogram,
    *,
    kernels: tuple[Kernel, ...] = KERNELS,
    plausible_ratio: float = 1.5,
    n_grid: int = 64,
) -> NoiseFit:
    """Fit nugget + sill + range of each kernel to a variogram; choose the best.

    Parameters
    ----------
    vg : Variogram
    kernels : tuple of str
        Kernels to try (see :data:`calib.stats.kernels.KERNELS`).
    plausible_ratio : float
        Kernels whose criterion is at most this times the best one's are kept in
        :attr:`NoiseFit.plausible` (>= 1).
    n_grid : int
        Log-spaced lengths tried before the scalar refinement.

    Returns
    -------
    NoiseFit
        ``best`` minimises Cressie's criterion ``sum N(h) (gamma_hat / gamma - 1)^2``.
    """
    if not kernels:
        raise NoiseModelError("no kernel to fit")
    if not np.max(vg.gamma_mm2) > 0:
        raise NoiseModelError("the variogram is zero: the residuals are constant within scans")
    if not plausible_ratio >= 1.0:
        raise NoiseModelError(f"plausible_ratio must be >= 1, got {plausible_ratio}")
    fits = tuple(_fit_kernel(vg, k, n_grid) for k in kernels)
    order = sorted(range(len(fits)), key=lambda i: fits[i].criterion)
    best = fits[order[0]]
    plausible = tuple(
        fits[i] for i in order if fits[i].criterion <= plausible_ratio * best.criterion
    )
    return NoiseFit(best, fits, plausible, vg)


def estimate_noise(
    sample: SurfaceSample,
    residual_mm: np.ndarray,
    *,
    max_lag_mm: float = MAX_LAG_MM,
    n_bins: int = N_BINS,
    max_pairs: int = MAX_PAIRS,
    detrend: Detrend = "none",
    scope: Literal["pooled", "per-scan"] = "pooled",
    kernels: tuple[Kernel, ...] = KERNELS,
    seed: int = 0,
) -> NoiseFit | dict[int, NoiseFit]:
    """Variogram and kernel fit in one call (the short-range estimate by default).

    Parameters
    ----------
    sample : SurfaceSample
    residual_mm : ndarray, shape (n,)
    max_lag_mm, n_bins, max_pairs, detrend, seed
        See :func:`empirical_variogram`.
    scope : {"pooled", "per-scan"}
        One model from the pairs of all scans, or one per scan (a dict by scan label).
    kernels : tuple of str

    Returns
    -------
    NoiseFit or dict of int to NoiseFit

    Raises
    ------
    NoiseModelError
        ``scope`` or ``detrend`` unknown, ``n_bins < 3``, ``kernels`` empty, fewer than 3
        distance bins with enough pairs, or a variogram that is zero (residuals constant
        within scans).
    SampleError
        ``residual_mm`` not one finite value per point, or ``max_lag_mm``/``max_pairs``
        not positive.
    """
    kw = dict(max_lag_mm=max_lag_mm, n_bins=n_bins, max_pairs=max_pairs, detrend=detrend,
              seed=seed)  # fmt: skip
    if scope == "pooled":
        return fit_variogram(empirical_variogram(sample, residual_mm, **kw), kernels=kernels)
    if scope != "per-scan":
        raise NoiseModelError(f"scope must be 'pooled' or 'per-scan', got {scope!r}")
    r = sample.check_values(residual_mm, "residual_mm")
    out = {}
    for label, idx in zip(sample.labels, sample.blocks, strict=True):
        sub = SurfaceSample(sample.points_mm[idx])
        out[label] = fit_variogram(empirical_variogram(sub, r[idx], **kw), kernels=kernels)
    return out


#: A scan's level is measured on the lags up to the quietest scan's this-many shortest
#: kept bins: a smooth misfit adds only about ``|grad m|^2 h^2 / 2`` there.
LEVEL_BINS = 3


def _short_semivariance(variogram: Variogram, upto_mm: float) -> float:
    """The pair-weighted mean semivariance of the bins up to ``upto_mm`` (mm^2).

    The first bin where none lies that near (a sparse scan).
    """
    keep = variogram.lag_mm <= upto_mm
    if not keep.any():
        keep = np.arange(len(variogram.lag_mm)) == 0
    w = variogram.n_pairs[keep]
    return float(np.sum(w * variogram.gamma_mm2[keep]) / np.sum(w))


def session_noise(
    sample: SurfaceSample, residual_mm: np.ndarray, *, by_scan: bool = False, **kw
) -> NoiseFit:
    """The least-disturbed scan's short-range noise fit, for every scan of a session.

    A missing effect only adds to a scan's residual, and in a short-range variogram it
    shows as a larger sill and a longer range. The session's noise model is therefore
    the per-scan fit (:func:`estimate_noise`, ``scope="per-scan"``) with the smallest
    standard deviation. With one scan it is that scan's fit.

    Each scan's level (``scan_sd_mm``) is that fit's sd times the square root of the
    scan's mean semivariance over the quietest's, at the lags up to its
    :data:`LEVEL_BINS` shortest bins. They tell imaging noise from model misfit only in
    part: a misfit that varies over a model element adds to them too (the quick skin
    twin of seed 0, whose scans are imaged alike: 0.33 mm on its right lateral scan,
    0.20 on its 50 degree one). So they are used only where the caller knows
    the scans are imaged unlike (another slice thickness, coil or SNR: ``by_scan``);
    then :meth:`NoiseFit.scaled` gives each scan the fit's correlation at its own level,
    and each scan's own fit is one more alternative (:attr:`NoiseFit.alternatives`).

    Parameters
    ----------
    sample : SurfaceSample
    residual_mm : ndarray, shape (n,)
    by_scan : bool
        Give each scan its own level (scans imaged unlike).
    **kw
        Passed to :func:`estimate_noise` (``max_lag_mm``, ...).

    Returns
    -------
    NoiseFit
    """
    fits = estimate_noise(sample, residual_mm, scope="per-scan", **kw)
    label = min(fits, key=lambda k: fits[k].best.sigma_mm)
    ref = fits[label]
    upto = float(ref.variogram.lag_mm[min(LEVEL_BINS, len(ref.variogram.lag_mm)) - 1])
    short = {k: _short_semivariance(f.variogram, upto) for k, f in fits.items()}
    sd = {k: ref.best.sigma_mm * float(np.sqrt(v / short[label])) for k, v in short.items()}
    own = {k: f.best for k, f in fits.items()}
    return replace(ref, scan_sd_mm=sd, scan_fits=own, reference_scan=label, by_scan=bool(by_scan))


# ------------------------------------------------------------------------ covariances


def covariance_matrix(sample: SurfaceSample, noise: NoiseArg) -> np.ndarray:
    """Dense block-diagonal covariance (mm^2) of the residual noise.

    Parameters
    ----------
    sample : SurfaceSample
        Every scan at most :data:`MAX_DENSE_BLOCK` points.
    noise : NoiseModel or mapping of scan label to NoiseModel

    Returns
    -------
    ndarray, shape (n, n)
        Zero between scans.
    """
    out = np.zeros((sample.n, sample.n))
    for b, (label, idx) in enumerate(zip(sample.labels, sample.blocks, strict=True)):
        m = _model_for(noise, label)
        out[np.ix_(idx, idx)] = m.sigma_mm**2 * m.correlation(sample.distances(b), same_points=True)
    return out


def apply_covariance(sample: SurfaceSample, noise: NoiseArg, x: np.ndarray) -> np.ndarray:
    """``Sigma x`` without storing ``Sigma`` when a scan is too large for a dense matrix.

    Parameters
    ----------
    sample : SurfaceSample
    noise : NoiseModel or mapping of scan label to NoiseModel
    x : ndarray, shape (n,) or (n, k)

    Returns
    -------
    ndarray, shape of ``x``
        In mm^2 times the units of ``x``.
    """
    from scipy.spatial.distance import cdist

    one = np.ndim(x) == 1
    xx = sample.check_values(x, "x", columns=True)
    out = np.zeros_like(xx)
    for b, (label, idx) in enumerate(zip(sample.labels, sample.blocks, strict=True)):
        m = _model_for(noise, label)
        s2 = m.sigma_mm**2
        if m.white:
            out[idx] = s2 * xx[idx]
            continue
        if len(idx) <= MAX_DENSE_BLOCK:
            out[idx] = s2 * (m.correlation(sample.distances(b), same_points=True) @ xx[idx])
            continue
        p = sample.points_mm[idx]
        for start in range(0, len(idx), CHUNK):
            rows = slice(start, start + CHUNK)
            rho = (1.0 - m.nugget_fraction) * correlation(m.kernel, cdist(p[rows], p), m.length_mm)
            out[idx[rows]] = s2 * (rho @ xx[idx] + m.nugget_fraction * xx[idx[rows]])
    return out[:, 0] if one else out


@dataclass(frozen=True, eq=False)
class Whitener:
    """Per-scan Cholesky factors ``Sigma_s = L_s L_s'`` of the noise covariance.

    Attributes
    ----------
    blocks : tuple of ndarray of int
        Point indices of each scan.
    factors : tuple of ndarray
        Lower-triangular ``L_s`` (mm), one per scan.
    """

    blocks: tuple[np.ndarray, ...]
    factors: tuple[np.ndarray, ...]

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``L^{-1} x`` per scan: unit-variance, uncorrelated under the model.

        Parameters
        ----------
        x : ndarray, shape (n,) or (n, k), in mm

        Returns
        -------
        ndarray, shape of ``x``, dimensionless
        """
        from scipy.linalg import solve_triangular

        x = np.asarray(x, dtype=float)
        out = np.empty_like(x)
        for idx, L in zip(self.blocks, self.factors, strict=True):
            out[idx] = solve_triangular(L, x[idx], lower=True, check_finite=False)
        return out

    def logdet(self) -> float:
        """``log det Sigma`` (Sigma in mm^2)."""
        return float(sum(2.0 * np.sum(np.log(np.diag(L))) for L in self.factors))


def whitener(sample: SurfaceSample, noise: NoiseArg, *, jitter: float = 1e-10) -> Whitener:
    """Cholesky factors of each scan's covariance (a diagonal ``jitter * sigma^2`` added).

    Parameters
    ----------
    sample : SurfaceSample
        Every scan at most :data:`MAX_DENSE_BLOCK` points (else use :func:`local_counts`).
    noise : NoiseModel or mapping of scan label to NoiseModel
    jitter : float
        Relative diagonal loading: a Gaussian kernel on dense points is numerically
        singular.

    Returns
    -------
    Whitener

    Raises
    ------
    NoiseModelError
        ``noise`` has no model for one of the scans, or a scan's correlation matrix is not
        positive definite even with ``jitter``.
    SampleError
        A scan has more than :data:`MAX_DENSE_BLOCK` points.
    """
    factors = []
    for b, (label, _idx) in enumerate(zip(sample.labels, sample.blocks, strict=True)):
        m = _model_for(noise, label)
        c = m.correlation(sample.distances(b), same_points=True)
        c[np.diag_indices_from(c)] += jitter
        try:
            factors.append(m.sigma_mm * np.linalg.cholesky(c))
        except np.linalg.LinAlgError:
            raise NoiseModelError(
                f"scan {label}: the noise correlation matrix is not positive definite "
                f"(kernel {m.kernel}, length {m.length_mm:.3g} mm); raise jitter"
            ) from None
    return Whitener(sample.blocks, tuple(factors))


def local_counts(sample: SurfaceSample, noise: NoiseArg) -> np.ndarray:
    """Local effective-sample divisor ``m_i = sum_j R_ij`` (correlation row sums).

    With ``R`` the correlation matrix (within the point's scan), ``Sigma x ~ sigma^2 m x``
    and ``Sigma^{-1} x ~ x / (sigma^2 m)`` for fields ``x`` that are constant over a
    correlation length; ``n^2 / sum(m)`` is the exact effective sample count of the
    scan mean. Cost ``O(n^2)`` time, ``O(CHUNK n)`` memory (rows in chunks of
    :data:`CHUNK`): usable where a Cholesky factor is not.

    Parameters
    ----------
    sample : SurfaceSample
    noise : NoiseModel or mapping of scan label to NoiseModel

    Returns
    -------
    ndarray, shape (n,)
        ``m_i >= 1``.
    """
    from scipy.spatial.distance import cdist

    m_out = np.empty(sample.n)
    for label, idx in zip(sample.labels, sample.blocks, strict=True):
        m = _model_for(noise, label)
        if m.white:
            m_out[idx] = 1.0
            continue
        p = sample.points_mm[idx]
        for start in range(0, len(idx), CHUNK):
            rows = slice(start, start + CHUNK)
            rho = correlation(m.kernel, cdist(p[rows], p), m.length_mm).sum(axis=1)
            m_out[idx[rows]] = m.nugget_fraction + (1.0 - m.nugget_fraction) * rho
    return m_out


def effective_sample_count(sample: SurfaceSample, noise: NoiseArg) -> float:
    """Effective number of independent residuals, ``sum_s n_s^2 / sum_ij R^(s)_ij``.

    ``Var(mean of scan s) = sigma^2 sum_ij R_ij / n_s^2``: each scan counts as
    ``n_s^2 / sum_ij R_ij`` independent residuals (exact for the mean: the localisation's
    region z-scores, :func:`calib.discrepancy.localise.significance_map`; the intervals
    do not use it). Cost ``O(n^2)`` time, ``O(CHUNK n)`` memory (:func:`local_counts`;
    20,000 points: 4 s and 0.7 GB).

    Parameters
    ----------
    sample : SurfaceSample
    noise : NoiseModel or mapping of scan label to NoiseModel

    Returns
    -------
    float
    """
    counts = local_counts(sample, noise)
    return float(sum(len(idx) ** 2 / np.sum(counts[idx]) for idx in sample.blocks))


def with_sigma(model: NoiseModel, sigma_mm: float) -> NoiseModel:
    """The same correlation with another standard deviation (mm)."""
    return replace(model, sigma_mm=float(sigma_mm))
