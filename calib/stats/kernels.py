"""Isotropic correlation kernels of the residual noise on a surface.

Three members of the Matérn family, parameterised as in Rasmussen & Williams (2006,
*Gaussian Processes for Machine Learning*, Ch. 4) so that ``length_mm`` means the same
thing for all of them up to the family's smoothness:

- ``exponential`` (Matérn 1/2): ``rho(h) = exp(-h / l)``            (R&W Eq. 4.18)
- ``matern32`` (Matérn 3/2):    ``rho(h) = (1 + s) exp(-s)``, ``s = sqrt(3) h / l``  (Eq. 4.17)
- ``gaussian`` (squared exponential): ``rho(h) = exp(-h^2 / (2 l^2))``  (Eq. 4.9)

All three have the same correlation area on a plane, ``int rho dA = 2 pi l^2``, which is
what sets the variance of a smooth weighted sum of the noise (the quantity an interval of
a smooth model parameter depends on). Distances are 3-D chord lengths in mm; a kernel
valid in 3-D restricted to points on a surface is still a valid covariance.

The estimate in ``calib/fitting/uncertainty.py`` uses the 1/e distance ``l_e`` and
``n_eff = A / (pi l_e^2)``: right for the Gaussian kernel (``l_e = sqrt(2) l``) and too
small an area by 2 for the exponential one (``l_e = l``), hence its under-coverage there.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

__all__ = [
    "KERNELS",
    "Kernel",
    "UnknownKernelError",
    "correlation",
    "correlation_area_mm2",
    "one_over_e_distance_mm",
    "truncation_distance_mm",
]

Kernel = Literal["exponential", "gaussian", "matern32"]
KERNELS: tuple[Kernel, ...] = ("exponential", "gaussian", "matern32")


class UnknownKernelError(ValueError):
    """A kernel name outside :data:`KERNELS`."""


def _check(kernel: str) -> None:
    if kernel not in KERNELS:
        raise UnknownKernelError(
            f"unknown correlation kernel {kernel!r}; expected one of {KERNELS}"
        )


def correlation(kernel: Kernel, distance_mm: np.ndarray, length_mm: float) -> np.ndarray:
    """Correlation ``rho(h)`` of the noise at two points ``h`` mm apart.

    Parameters
    ----------
    kernel : {"exponential", "gaussian", "matern32"}
    distance_mm : ndarray, any shape
        Non-negative distances, mm.
    length_mm : float
        Length scale ``l`` (mm, >= 0). ``0`` is white noise: ``rho = 1`` at ``h = 0`` only.

    Returns
    -------
    ndarray, same shape as ``distance_mm``
        Correlations in [0, 1].

    Raises
    ------
    UnknownKernelError
        ``kernel`` is not one of :data:`KERNELS`.
    """
    _check(kernel)
    h0 = np.asarray(distance_mm, dtype=float)
    if not length_mm > 0:
        return (h0 == 0.0).astype(float)
    out = _rho(kernel, np.atleast_1d(h0), float(length_mm))
    return out.reshape(h0.shape)


def _rho(kernel: Kernel, h: np.ndarray, length_mm: float) -> np.ndarray:
    """The kernels on an array of at least one dimension (in-place arithmetic)."""
    if kernel == "exponential":
        out = np.multiply(h, -1.0 / length_mm)
        return np.exp(out, out=out)  # Eq. (4.18), R&W 2006
    if kernel == "gaussian":
        out = np.multiply(h, h)
        out *= -0.5 / length_mm**2
        return np.exp(out, out=out)  # Eq. (4.9)
    s = np.multiply(h, np.sqrt(3.0) / length_mm)
    out = np.exp(-s)
    s += 1.0
    out *= s
    return out  # Eq. (4.17): (1 + s) exp(-s)


def correlation_area_mm2(kernel: Kernel, length_mm: float) -> float:
    """Integral of ``rho`` over a plane, ``2 pi l^2`` for all three kernels (mm^2)."""
    _check(kernel)
    return float(2.0 * np.pi * length_mm**2)


def one_over_e_distance_mm(kernel: Kernel, length_mm: float) -> float:
    """Distance at which ``rho`` falls to 1/e (mm)."""
    _check(kernel)
    if kernel == "exponential":
        return float(length_mm)
    if kernel == "gaussian":
        return float(np.sqrt(2.0) * length_mm)
    # (1 + s) exp(-s) = exp(-1): s = 2.1462 (solved once, Newton)
    return float(2.1461932206205825 / np.sqrt(3.0) * length_mm)


def truncation_distance_mm(kernel: Kernel, length_mm: float, *, tol: float = 1e-4) -> float:
    """Distance beyond which ``rho < tol`` (mm): where a sparse sum may stop."""
    _check(kernel)
    if kernel == "exponential":
        return float(-np.log(tol) * length_mm)
    if kernel == "gaussian":
        return float(np.sqrt(-2.0 * np.log(tol)) * length_mm)
    # (1 + s) e^-s < tol: s = -ln tol + ln(1 + s), a few fixed-point steps
    s = -np.log(tol)
    for _ in range(20):
        s = -np.log(tol) + np.log1p(s)
    return float(s / np.sqrt(3.0) * length_mm)
