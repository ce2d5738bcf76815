"""A noise level that varies with one coordinate: the residual's spread by height band.

The diagnosis' noise model (:mod:`calib.stats.noise`) is stationary: one sill for every
point of a scan. On a phantom clamped to a back plate it is not. The surface meets the
plate at a stress singularity that a model mesh resolves slowly, and the scan's surface
extraction blurs the junction; the residual's spread near the plate is 2-4 times that
far from it on the twins' null sets (``benchmarks/bench_diagnose.py --rim-profile``).
A stationary model then takes the rim's misfit for the noise of every point, which
costs power away from the plate, and the rim's points dominate every projection.

:func:`height_profile` measures the spread per height band: a robust scale (the median
absolute deviation about the band's median, times 1.4826, consistent for a Gaussian;
Huber & Ronchetti 2009, Sec. 5.1) of the residual per band, relative to the farthest
band, made non-increasing with height (the plate is the one source of extra spread) and
never below 1. Dividing each residual, and each column of its derivatives, by its
band's relative spread (weighted least squares, Carroll & Ruppert 1988, ch. 3) leaves
a residual whose spread does not depend on height, to which the stationary model
applies; the far band keeps its units (mm).

References
----------
Carroll, R. J. & Ruppert, D. (1988). *Transformation and Weighting in Regression*.
Chapman & Hall.
Huber, P. J. & Ronchetti, E. M. (2009). *Robust Statistics*, 2nd ed. Wiley.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HEIGHT_BANDS_MM", "HeightProfile", "height_profile"]

#: Band edges (mm above the plate) of the profile: fine where the spread changes (one
#: 14-18 mm model element from the plate), one band beyond 30 mm.
HEIGHT_BANDS_MM = (0.0, 5.0, 8.0, 12.0, 16.0, 20.0, 30.0, np.inf)
#: Fewer points than this in a band: the band takes the value of the next one out.
MIN_BAND_POINTS = 30
_MAD_TO_SD = 1.4826  # 1 / Phi^-1(3/4): the MAD of a Gaussian is 0.6745 sd


@dataclass(frozen=True)
class HeightProfile:
    """Relative spread of a residual per height band.

    Attributes
    ----------
    edges_mm : tuple of float
        Band edges, increasing, from 0 to ``inf``.
    relative_sd : tuple of float
        Spread of each band over the farthest band's, non-increasing, >= 1.
    counts : tuple of int
        Points per band that measured it.
    far_sd_mm : float
        Robust spread of the farthest band (mm).
    """

    edges_mm: tuple
    relative_sd: tuple
    counts: tuple
    far_sd_mm: float

    def scale(self, height_mm: np.ndarray) -> np.ndarray:
        """The relative spread at each height (mm above the plate), shape of ``height_mm``."""
        band = np.digitize(np.asarray(height_mm, float), self.edges_mm[1:-1])
        return np.asarray(self.relative_sd, float)[band]

    def weights(self, height_mm: np.ndarray) -> np.ndarray:
        """``1 / scale``: what each residual and its derivatives are multiplied by."""
        return 1.0 / self.scale(height_mm)

    def as_json(self) -> dict:
        """Plain JSON types (``diagnosis.json``'s ``noise.height_profile``)."""
        return {
            "edges_mm": [float(e) if np.isfinite(e) else None for e in self.edges_mm],
            "relative_sd": [float(v) for v in self.relative_sd],
            "counts": [int(c) for c in self.counts],
            "far_sd_mm": float(self.far_sd_mm),
        }


def height_profile(
    height_mm: np.ndarray,
    residual_mm: np.ndarray,
    *,
    edges_mm: tuple = HEIGHT_BANDS_MM,
    min_points: int = MIN_BAND_POINTS,
) -> HeightProfile:
    """Measure the relative spread of a residual per height band.

    Parameters
    ----------
    height_mm : ndarray, shape (n,)
        Each residual's height above the plate (mm).
    residual_mm : ndarray, shape (n,)
        Residuals (mm), each scan's offset already removed.
    edges_mm : tuple of float
        Band edges, increasing from 0, the last ``inf``.
    min_points : int
        A band with fewer points takes the value of the next band out.

    Returns
    -------
    HeightProfile

    Raises
    ------
    ValueError
        Shapes differ, bad edges, or fewer than ``min_points`` points in the farthest
        band that has any.
    """
    h = np.asarray(height_mm, float)
    r = np.asarray(residual_mm, float)
    if h.shape != r.shape or h.ndim != 1:
        raise ValueError(f"height_mm {h.shape} and residual_mm {r.shape} must be equal 1-D shapes")
    e = np.asarray(edges_mm, float)
    if e[0] != 0.0 or not np.isinf(e[-1]) or np.any(np.diff(e) <= 0):
        raise ValueError(f"edges_mm must increase from 0 to inf, got {tuple(edges_mm)}")
    band = np.digitize(h, e[1:-1])
    counts = np.bincount(band, minlength=len(e) - 1)
    sd = np.full(len(e) - 1, np.nan)
    for k in np.flatnonzero(counts >= min_points):
        x = r[band == k]
        sd[k] = _MAD_TO_SD * np.median(np.abs(x - np.median(x)))
    measured = np.flatnonzero(np.isfinite(sd))
    if measured.size == 0:
        raise ValueError(f"no height band holds {min_points} residuals (of {h.size})")
    far = sd[measured[-1]]
    if not far > 0:
        raise ValueError("the farthest band's residuals have no spread")
    rel = np.ones_like(sd)
    rel[measured] = sd[measured] / far
    # >= 1 and non-increasing with height: the running maximum from the far side, which
    # also gives a band too thin to measure (1 here) the next band out's value
    rel = np.maximum.accumulate(np.maximum(rel, 1.0)[::-1])[::-1]
    return HeightProfile(
        tuple(float(x) for x in e),
        tuple(float(x) for x in rel),
        tuple(int(c) for c in counts),
        float(far),
    )
