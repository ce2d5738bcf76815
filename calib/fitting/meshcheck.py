"""Discretisation uncertainty of the calibrated c1: a grid-convergence check.

The calibrated c1 depends on the model mesh: a coarser mesh is stiffer, and it is
matched by a different c1. Residual noise says nothing about that. After the
calibration, the objective's gradient and Gauss-Newton curvature are evaluated once on
a mesh whose element size is ``ratio`` times the calibration mesh's (coarser for
``ratio > 1``, cheap; finer for ``ratio < 1``, costly but closer to the limit); one
Gauss-Newton step gives the c1 that mesh would calibrate to. With ``ln c1(h) = L + C h^p``
and the observed order ``p`` of the FE on the phantom (tests/fem/test_fem_convergence.py:
1.6), Richardson's estimate of the error left on the calibration mesh is
``|ln c1_check - ln c1| / |ratio**p - 1|``; Roache's grid convergence index multiplies it
by a safety factor (1.25 when the order is observed) and is read as a 95 % bound. It is
combined with the noise interval in quadrature. A check that cannot be solved (a mesh
too coarse to unload, say) is reported as failed, never silently skipped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from .options import check_mesh_check_ratio

__all__ = ["MeshCheck", "combined_ci95", "mesh_check"]

log = logging.getLogger(__name__)
OBSERVED_ORDER = 1.6
SAFETY_FACTOR = 1.25


@dataclass(frozen=True)
class MeshCheck:
    """Result of :func:`mesh_check`.

    Attributes
    ----------
    mesh_size_mm, check_mesh_size_mm : float
        Element sizes of the calibration mesh and of the check mesh.
    check_tets : int
    c1_check_pa : float or None
        The c1 the check mesh calibrates to (one Gauss-Newton step), Pa; None if failed.
    gci_ln_c1 : float or None
        Grid convergence index of ln c1 (a 95 % bound of the discretisation error).
    failure : str
        Why the check failed ("" when it did not).
    order, safety_factor : float
    """

    mesh_size_mm: float
    check_mesh_size_mm: float
    check_tets: int
    c1_check_pa: float | None
    gci_ln_c1: float | None
    failure: str = ""
    order: float = OBSERVED_ORDER
    safety_factor: float = SAFETY_FACTOR


def mesh_check(cal, theta: float, *, ratio: float = 1.4) -> MeshCheck:
    """Re-evaluate the calibration at ``theta = ln c1`` on a mesh ``ratio`` times as coarse.

    Parameters
    ----------
    cal : Calibrator
        The finished calibration (its measurements and options are reused).
    theta : float
        Calibrated ln c1 (c1 in Pa).
    ratio : float
        Element-size ratio of the check mesh, in [0.5, 0.9] (finer) or [1.1, 3] (coarser).

    Returns
    -------
    MeshCheck
    """
    import fem

    from .objective import Calibrator

    check_mesh_check_ratio(ratio)
    size = cal.options.mesh_size_mm
    opts = replace(cal.options, mesh_size_mm=size * ratio)
    tets, failure = 0, ""
    try:
        check = Calibrator(cal.measurements, opts, density_kg_m3=cal.density_kg_m3)
        tets = check.mesh.n_tets
        check.fm.fixed_point_fallback = False
        _, g = check.objective(np.array([theta]))
        step = -float(g[0]) / check.gauss_newton_curvature
    except (fem.MeshError, fem.ConvergenceError, ValueError, ZeroDivisionError) as exc:
        failure = f"{type(exc).__name__}: {exc}"
    else:
        if not np.isfinite(step):
            failure = "the Gauss-Newton step on the check mesh is not finite"
    if failure:
        log.warning("mesh check on the %.1f mm mesh failed (%s)", size * ratio, failure)
        return MeshCheck(size, size * ratio, tets, None, None, failure)
    error = abs(step) / abs(ratio**OBSERVED_ORDER - 1.0)
    return MeshCheck(size, size * ratio, tets, float(np.exp(theta + step)),
                     SAFETY_FACTOR * error)  # fmt: skip


def combined_ci95(
    c1_pa: float, se_ln_c1: float, gci_ln_c1: float, *, critical_value: float = 1.96
) -> tuple[float, float]:
    """95 % interval of c1 from the noise (``critical_value * se``) and the GCI, in quadrature.

    ``critical_value``: the noise interval's own (the series interval's Imhof quantile;
    1.96 for a normal one).
    """
    half = float(np.hypot(critical_value * se_ln_c1, gci_ln_c1))
    return c1_pa * float(np.exp(-half)), c1_pa * float(np.exp(half))
