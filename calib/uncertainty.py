"""Uncertainty of the calibrated c1: Gauss-Newton with effective sample counts.

Surface residuals are spatially correlated, so the number of independent samples is
the measured area over the area of one correlation patch, not the vertex count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Uncertainty", "correlation_length_mm", "gauss_newton_uncertainty"]


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
        estimate their noise (a single residual: the ``nipple`` objective).
    c1_ci95_pa : tuple of float or None
    residual_sd_mm : float
        Residual noise estimate.
    n_residuals, n_effective : float
        Residual count and effective independent samples.
    correlation_length_mm : float
    """

    se_ln_c1: float | None
    c1_ci95_pa: tuple[float, float] | None
    residual_sd_mm: float
    n_residuals: int
    n_effective: float
    correlation_length_mm: float


def gauss_newton_uncertainty(
    c1_pa: float, r: np.ndarray, dr: np.ndarray, points_mm: np.ndarray, *, area_mm2: float | None
) -> Uncertainty:
    """Gauss-Newton standard error of ln c1, inflated by ``n / n_eff``.

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
    n = len(r)
    if n < 2:  # one residual and one parameter: no degree of freedom left for the noise
        return Uncertainty(None, None, float(np.abs(r).sum()), n, float(n), 0.0)
    sd = float(np.sqrt(np.sum(r**2) / (n - 1)))
    ell = correlation_length_mm(points_mm, r) if area_mm2 else 0.0
    n_eff = (
        float(n) if not area_mm2 or ell == 0 else float(np.clip(area_mm2 / (np.pi * ell**2), 2, n))
    )
    info = float(np.sum(dr**2))
    se = sd / np.sqrt(info) * np.sqrt(n / n_eff) if info > 0 else np.inf
    ci = (c1_pa * float(np.exp(-1.96 * se)), c1_pa * float(np.exp(1.96 * se)))
    return Uncertainty(float(se), ci, sd, n, n_eff, ell)
