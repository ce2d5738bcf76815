"""Where the residuals live: points on measured surfaces, grouped by scan.

Scans are independent measurements (separate MR acquisitions), so every covariance in
this package is block-diagonal by scan, and no variogram pair ever joins two scans, even
where their points overlap in the reference frame. :class:`SurfaceSample` checks the
inputs once and caches what depends on the geometry only (scan blocks, dense distance
matrices for blocks up to :data:`MAX_DENSE_BLOCK` points, variogram pair sets), so
that repeated statistics on the same geometry (a coverage study, a bootstrap) do not
redo them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

__all__ = ["MAX_DENSE_BLOCK", "MAX_PAIRS", "PairSet", "SampleError", "SurfaceSample"]

MAX_DENSE_BLOCK = 4000  # a 4000 x 4000 float64 matrix is 128 MB
#: Most point pairs a variogram takes (seeded thinning beyond).
MAX_PAIRS = 400_000


class SampleError(ValueError):
    """Points, scan labels or a per-point array that do not fit together."""


@dataclass(frozen=True, eq=False)
class PairSet:
    """Point pairs within one scan, closer than ``max_lag_mm`` (a variogram's pairs).

    Attributes
    ----------
    i, j : ndarray of int, shape (m,)
        Indices into the sample's points (``i < j``, same scan).
    distance_mm : ndarray, shape (m,)
    max_lag_mm : float
    thinned : bool
        True when the pairs were subsampled (seeded) to stay within ``max_pairs``.
    seed : int
    """

    i: np.ndarray
    j: np.ndarray
    distance_mm: np.ndarray
    max_lag_mm: float
    thinned: bool
    seed: int
    _bins: dict = field(default_factory=dict, repr=False)

    def bins(self, n_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bin of each pair among ``n_bins`` equal bins on ``(0, max_lag_mm]`` (cached).

        Returns
        -------
        index : ndarray of int, shape (m,)
        count : ndarray of int, shape (n_bins,)
        mean_distance_mm : ndarray, shape (n_bins,)
            Mean pair distance per bin (0 where empty).
        """
        if n_bins not in self._bins:
            edges = np.linspace(0.0, self.max_lag_mm, n_bins + 1)
            b = np.searchsorted(edges, self.distance_mm, side="right") - 1
            b = np.clip(b, 0, n_bins - 1)
            count = np.bincount(b, minlength=n_bins)
            lag = np.bincount(b, weights=self.distance_mm, minlength=n_bins) / np.maximum(count, 1)
            self._bins[n_bins] = (b, count, lag)
        return self._bins[n_bins]


@dataclass(frozen=True, eq=False)
class SurfaceSample:
    """Points (mm) on measured surfaces with their scan labels.

    Parameters
    ----------
    points_mm : ndarray, shape (n, 3)
        Residual locations in one frame (mm).
    scan : ndarray of int, shape (n,), optional
        Scan label of each point; default: one scan.
    """

    points_mm: np.ndarray
    scan: np.ndarray | None = None
    _pairs: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.points_mm, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
            raise SampleError(f"points_mm must have shape (n, 3) with n >= 1, got {p.shape}")
        if not np.isfinite(p).all():
            raise SampleError("points_mm holds non-finite coordinates")
        s = np.zeros(len(p), dtype=np.int64) if self.scan is None else np.asarray(self.scan)
        if s.shape != (len(p),):
            raise SampleError(f"scan must have shape ({len(p)},) like points_mm, got {s.shape}")
        if not np.issubdtype(s.dtype, np.integer):
            raise SampleError(f"scan labels must be integers, got dtype {s.dtype}")
        object.__setattr__(self, "points_mm", p)
        object.__setattr__(self, "scan", s.astype(np.int64))

    @property
    def n(self) -> int:
        """Number of points."""
        return len(self.points_mm)

    @cached_property
    def labels(self) -> tuple[int, ...]:
        """Scan labels, sorted."""
        return tuple(int(v) for v in np.unique(self.scan))

    @cached_property
    def blocks(self) -> tuple[np.ndarray, ...]:
        """Point indices of each scan, in the order of :attr:`labels`."""
        return tuple(np.flatnonzero(self.scan == s) for s in self.labels)

    def check_values(self, values: np.ndarray, name: str, *, columns: bool = False) -> np.ndarray:
        """``values`` as float, checked to have one row per point and to be finite.

        Parameters
        ----------
        values : ndarray, shape (n,) or (n, k)
            One value (or row) per point, in the caller's unit (e.g. residuals in mm).
        name : str
            Used in the error message.
        columns : bool
            Accept (and return) a 2-D array; a 1-D one becomes (n, 1).

        Returns
        -------
        ndarray, shape (n,) or (n, k) float
            ``values`` as a float array, unit unchanged.

        Raises
        ------
        SampleError
            ``values`` has not one row per point, or holds non-finite values.
        """
        v = np.asarray(values, dtype=float)
        if columns and v.ndim == 1:
            v = v[:, None]
        want = 2 if columns else 1
        if v.ndim != want or v.shape[0] != self.n:
            shape = f"({self.n}, k)" if columns else f"({self.n},)"
            raise SampleError(f"{name} must have shape {shape} (one row per point), got {v.shape}")
        if not np.isfinite(v).all():
            raise SampleError(f"{name} holds non-finite values")
        return v

    def distances(self, block: int) -> np.ndarray:
        """Dense distance matrix (mm) of scan block ``block`` (cached).

        Parameters
        ----------
        block : int
            Position of the scan in :attr:`labels` / :attr:`blocks` (not its label).

        Returns
        -------
        ndarray, shape (m, m) float
            Distances between the block's ``m`` points, mm.

        Raises
        ------
        SampleError
            When the block has more than :data:`MAX_DENSE_BLOCK` points.
        """
        key = ("dist", block)
        if key not in self._pairs:
            idx = self.blocks[block]
            if len(idx) > MAX_DENSE_BLOCK:
                raise SampleError(
                    f"scan {self.labels[block]} has {len(idx)} points; dense matrices are "
                    f"limited to {MAX_DENSE_BLOCK} (use the sparse/effective-sample paths)"
                )
            from scipy.spatial.distance import cdist

            p = self.points_mm[idx]
            self._pairs[key] = cdist(p, p)
        return self._pairs[key]

    def pairs(self, max_lag_mm: float, *, max_pairs: int = MAX_PAIRS, seed: int = 0) -> PairSet:
        """All within-scan pairs closer than ``max_lag_mm``, seeded-thinned to ``max_pairs``.

        Parameters
        ----------
        max_lag_mm : float
            Largest pair distance kept (mm, > 0).
        max_pairs : int
            When more pairs qualify, a uniform seeded subset of this size is kept.
        seed : int

        Returns
        -------
        PairSet

        Raises
        ------
        SampleError
            ``max_lag_mm`` not positive or ``max_pairs < 1``.
        """
        if not max_lag_mm > 0:
            raise SampleError(f"max_lag_mm must be positive, got {max_lag_mm}")
        if max_pairs < 1:
            raise SampleError(f"max_pairs must be >= 1, got {max_pairs}")
        key = ("pairs", float(max_lag_mm), int(max_pairs), int(seed))
        if key not in self._pairs:
            self._pairs[key] = self._find_pairs(float(max_lag_mm), int(max_pairs), int(seed))
        return self._pairs[key]

    def _find_pairs(self, max_lag: float, max_pairs: int, seed: int) -> PairSet:
        from scipy.spatial import cKDTree

        rng = np.random.default_rng(seed)
        ii, jj, thinned = [], [], False
        for idx in self.blocks:
            p = self.points_mm[idx]
            tree = cKDTree(p)
            # thin the points first where the pairs alone would not fit in memory: keeping
            # a fraction q of the points keeps about q^2 of the pairs
            probe = rng.choice(len(p), min(len(p), 200), replace=False)
            per_point = np.mean([len(v) for v in tree.query_ball_point(p[probe], max_lag)]) - 1
            expected = 0.5 * len(p) * per_point
            keep = np.arange(len(p))
            if expected > 8 * max_pairs:
                q = np.sqrt(4 * max_pairs / expected)
                keep = np.sort(rng.choice(len(p), max(2, int(q * len(p))), replace=False))
                tree, thinned = cKDTree(p[keep]), True
            pr = tree.query_pairs(max_lag, output_type="ndarray")
            ii.append(idx[keep[pr[:, 0]]])
            jj.append(idx[keep[pr[:, 1]]])
        i, j = np.concatenate(ii), np.concatenate(jj)
        if len(i) > max_pairs:
            sub = np.sort(rng.choice(len(i), max_pairs, replace=False))
            i, j, thinned = i[sub], j[sub], True
        d = np.linalg.norm(self.points_mm[i] - self.points_mm[j], axis=1)
        return PairSet(i, j, d, max_lag, thinned, seed)
