"""Smooth per-scan modes: polynomials in each scan's coordinates, orthonormalised.

The interval, the misfit test and the effect scores all look at a residual through a few
smooth weightings of it. Here they are monomials of degree ``0..d`` in each scan's
centred, scaled coordinates (zero on the other scans), optionally multiplied by a weight
field, with whatever the fitted parameters can absorb projected out, and orthonormalised
in order of degree (low degrees keep their shape). On a sphere or ellipsoid some
monomials are dependent (``x^2 + y^2 + z^2 = 1``): those columns are dropped.
"""

from __future__ import annotations

import itertools

import numpy as np

from .sample import SurfaceSample

__all__ = ["orthonormalise", "project_out", "scan_polynomials"]


def scan_polynomials(
    sample: SurfaceSample, degree: int, *, min_degree: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Monomials of degree ``min_degree..degree`` in each scan's own coordinates.

    Coordinates are centred on the scan's mean point and divided by its RMS radius, so
    the columns are of order one whatever the size of the scan.

    Parameters
    ----------
    sample : SurfaceSample
    degree, min_degree : int
        Total-degree range, ``0 <= min_degree <= degree``.

    Returns
    -------
    basis : ndarray, shape (n, k)
        ``k = n_scans * (C(degree + 3, 3) - C(min_degree + 2, 3))``; zero off its scan.
    degrees : ndarray of int, shape (k,)
        Total degree of each column.
    """
    if not 0 <= min_degree <= degree:
        raise ValueError(f"need 0 <= min_degree <= degree, got {min_degree}, {degree}")
    cols, degs = [], []
    for idx in sample.blocks:
        x = sample.points_mm[idx] - sample.points_mm[idx].mean(axis=0)
        x /= max(float(np.sqrt(np.mean(np.sum(x**2, axis=1)))), 1e-12)
        for d in range(min_degree, degree + 1):
            for combo in itertools.combinations_with_replacement(range(3), d):
                col = np.zeros(sample.n)
                col[idx] = np.prod(x[:, list(combo)], axis=1) if combo else 1.0
                cols.append(col)
                degs.append(d)
    return np.column_stack(cols), np.asarray(degs, dtype=np.int64)


def project_out(columns: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``x`` minus its least-squares projection on the span of ``columns``.

    Parameters
    ----------
    columns : ndarray, shape (n, p)
    x : ndarray, shape (n,) or (n, k)

    Returns
    -------
    ndarray, shape of ``x``
        ``(I - C (C'C)^+ C') x`` with ``C = columns``: the residual maker of a linear fit.
    """
    c = np.asarray(columns, dtype=float)
    if c.ndim == 1:
        c = c[:, None]
    coef, *_ = np.linalg.lstsq(c, x, rcond=None)
    return x - c @ coef


def orthonormalise(
    x: np.ndarray, *, against: np.ndarray | None = None, rtol: float = 1e-6
) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal columns spanning ``x`` (in column order), orthogonal to ``against``.

    Modified Gram-Schmidt with one re-orthogonalisation ("twice is enough", Giraud et
    al. 2005); a column whose part outside the span of the earlier ones is below
    ``rtol`` times its own norm is dropped.

    Parameters
    ----------
    x : ndarray, shape (n, k)
    against : ndarray, shape (n, p), optional
        Columns to stay orthogonal to (they need not be orthonormal).
    rtol : float

    Returns
    -------
    q : ndarray, shape (n, k')
    kept : ndarray of int, shape (k',)
        Indices of the columns of ``x`` that were kept.
    """
    x = np.asarray(x, dtype=float)
    basis: list[np.ndarray] = []
    if against is not None:
        a = np.asarray(against, dtype=float)
        a = a[:, None] if a.ndim == 1 else a
        qa, ra = np.linalg.qr(a)
        diag = np.abs(np.diag(ra))
        basis.extend(qa[:, diag > rtol * max(diag.max(initial=0.0), 1e-300)].T)
    n_fixed = len(basis)
    kept = []
    for k in range(x.shape[1]):
        v = x[:, k].copy()
        norm0 = np.linalg.norm(v)
        if norm0 == 0:
            continue
        for _ in range(2):
            for b in basis:
                v -= (b @ v) * b
        norm = np.linalg.norm(v)
        if norm > rtol * norm0:
            basis.append(v / norm)
            kept.append(k)
    q = np.array(basis[n_fixed:]).T if len(basis) > n_fixed else np.zeros((x.shape[0], 0))
    return q, np.asarray(kept, dtype=np.int64)
