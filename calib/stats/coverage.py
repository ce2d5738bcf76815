"""Cheap linear models on realistic geometry, for coverage and false-alarm studies.

A scan is a set of points spread uniformly by area over the upper half of an ellipsoid
(semi-axes 75, 75, 60 mm: a 150 mm wide phantom); several scans of one session lie on
the same surface (the reference frame) with their own points and independent noise.
The sensitivity ``dr / d ln c1`` of a scan is a smooth field that vanishes at the
clamped rim (``z = 0``) and peaks at the apex, tilted by the scan's posture angle, like
the normal component of a sagging dome's displacement. Noise is drawn exactly (Cholesky
per scan) from a :class:`calib.stats.noise.NoiseModel`. Everything takes a seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .noise import NoiseArg, covariance_matrix
from .sample import SurfaceSample

__all__ = [
    "NoiseSampler",
    "ellipsoid_points",
    "misfit_pattern",
    "phantom_sample",
    "sag_sensitivity",
]

SEMI_AXES_MM = (75.0, 75.0, 60.0)


def ellipsoid_points(
    n: int, *, seed: int, semi_axes_mm: tuple[float, float, float] = SEMI_AXES_MM
) -> np.ndarray:
    """``n`` points uniform by area on the upper half (``z >= 0``) of an ellipsoid.

    Directions uniform on the sphere are mapped onto the ellipsoid and thinned by the
    ratio of the mapped area element to its largest value (rejection sampling).

    Parameters
    ----------
    n : int
    seed : int
    semi_axes_mm : tuple of float
        ``(a, b, c)`` in mm.

    Returns
    -------
    ndarray, shape (n, 3)
        mm.
    """
    a, b, c = semi_axes_mm
    rng = np.random.default_rng(seed)
    out, have = [], 0
    while have < n:
        v = rng.normal(size=(4 * n + 16, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v[:, 2] = np.abs(v[:, 2])
        # area element of x = diag(a, b, c) v on the unit sphere: |(bc v1, ac v2, ab v3)|
        dens = np.linalg.norm(v * np.array([b * c, a * c, a * b]), axis=1)
        keep = rng.random(len(v)) < dens / (max(a * b, b * c, a * c))
        out.append(v[keep] * np.array([a, b, c]))
        have += int(keep.sum())
    return np.concatenate(out)[:n]


def phantom_sample(n_per_scan: int, n_scans: int = 1, *, seed: int = 0) -> SurfaceSample:
    """``n_scans`` scans of ``n_per_scan`` points each on the phantom's surface."""
    pts = [ellipsoid_points(n_per_scan, seed=seed * 1000 + s) for s in range(n_scans)]
    scan = np.repeat(np.arange(n_scans), n_per_scan)
    return SurfaceSample(np.concatenate(pts), scan)


def sag_sensitivity(sample: SurfaceSample, *, posture_deg: tuple[float, ...] = ()) -> np.ndarray:
    """Smooth ``dr / d ln c1`` (mm): ``-(z / c) (1 + 0.3 (x cos a + y sin a) / a)``.

    Parameters
    ----------
    sample : SurfaceSample
    posture_deg : tuple of float
        Tilt angle of each scan's field (by scan order); default ``0, 120, 240, ...``.

    Returns
    -------
    ndarray, shape (n,)
    """
    a, _, c = SEMI_AXES_MM
    x, y, z = sample.points_mm.T
    out = np.empty(sample.n)
    for k, idx in enumerate(sample.blocks):
        ang = np.deg2rad(posture_deg[k] if k < len(posture_deg) else 120.0 * k)
        tilt = (x[idx] * np.cos(ang) + y[idx] * np.sin(ang)) / a
        out[idx] = -(z[idx] / c) * (1.0 + 0.3 * tilt)
    return out


def misfit_pattern(sample: SurfaceSample, *, kind: str = "p2") -> np.ndarray:
    """A smooth, large-scale residual pattern of unit RMS (the shape of a missed effect).

    ``"p2"``: the Legendre ``P2`` of the polar height ``z / c`` (apex and rim against
    the flank, the shape a stiff skin absorbed into c1 leaves); ``"tilt"``: ``x / a``
    times ``z / c``; ``"bump"``: a Gaussian bump of 30 mm at the apex.

    Returns
    -------
    ndarray, shape (n,)
        Dimensionless; multiply by an amplitude in mm.
    """
    a, _, c = SEMI_AXES_MM
    x, _, z = sample.points_mm.T
    if kind == "p2":
        t = z / c
        m = 1.5 * t * t - 0.5
    elif kind == "tilt":
        m = (x / a) * (z / c)
    elif kind == "bump":
        d2 = np.sum((sample.points_mm - np.array([0.0, 0.0, c])) ** 2, axis=1)
        m = np.exp(-0.5 * d2 / 30.0**2)
    else:
        raise ValueError(f"unknown misfit pattern {kind!r}; expected 'p2', 'tilt' or 'bump'")
    m = m - m.mean()
    return m / np.sqrt(np.mean(m * m))


@dataclass(frozen=True, eq=False)
class NoiseSampler:
    """Exact draws of block-diagonal Gaussian noise (Cholesky per scan).

    Build with :meth:`of`; :meth:`draw` returns ``(n, size)`` noise in mm.
    """

    sample: SurfaceSample
    factors: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, sample: SurfaceSample, noise: NoiseArg, *, jitter: float = 1e-10):
        """Factorise the covariance of ``noise`` on ``sample`` once."""
        cov = covariance_matrix(sample, noise)
        scale = float(np.mean(np.diag(cov)))
        factors = tuple(
            np.linalg.cholesky(cov[np.ix_(idx, idx)] + jitter * scale * np.eye(len(idx)))
            for idx in sample.blocks
        )
        return cls(sample, factors)

    def draw(self, rng: np.random.Generator, size: int = 1) -> np.ndarray:
        """``size`` independent noise vectors, shape (n, size), mm."""
        out = np.empty((self.sample.n, size))
        for idx, L in zip(self.sample.blocks, self.factors, strict=True):
            out[idx] = L @ rng.standard_normal((len(idx), size))
        return out
