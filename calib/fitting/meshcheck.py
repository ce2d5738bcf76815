"""Discretisation uncertainty of the calibrated c1: a grid-convergence check.

The calibrated c1 depends on the model mesh: a coarser mesh is stiffer, and it is
matched by a different c1. Residual noise says nothing about that. After the
calibration, the objective's gradient and Gauss-Newton curvature are evaluated once on
each check mesh, whose element size is ``ratio`` times the calibration mesh's (coarser
for ``ratio > 1``, cheap; finer for ``ratio < 1``, costly but closer to the limit); one
Gauss-Newton step gives the c1 that mesh would calibrate to. With ``ln c1(h) = L + C h^p``:

* **One check mesh** (two meshes in all) assumes the order ``p`` of the FE on the phantom
  (tests/fem/test_fem_convergence.py: 1.6). Richardson's estimate of the error left on the
  calibration mesh is ``|ln c1_check - ln c1| / |ratio**p - 1|``; Roache's grid
  convergence index multiplies it by a safety factor of 1.25 and is read as a 95 % bound.
* **Two check meshes**, one coarser (``r``) and one finer (``1/r``): the order is observed,
  ``p = ln(e_coarse / e_fine) / ln r`` with ``e_coarse = ln c1 - ln c1(r h)`` and
  ``e_fine = ln c1(h / r) - ln c1`` (Roache 1998, Ch. 5). Where it lies in
  [0.5, 4] (the asymptotic range; the same bounds as ``benchmarks/bench_fem.py``) the GCI
  is ``1.25 |e_fine| / (1 - r**-p)``. Where it does not (the changes grow under refinement,
  or change sign) the meshes are not in the asymptotic range and Richardson does not
  apply: the bound is ``3 * max|ln c1_i - ln c1_j|`` over the three meshes, the data range
  with a safety factor of 3, Eça & Hoekstra's rule for anomalous behaviour (2014).

The bound is combined with the noise interval in quadrature. A check that cannot be solved
(a mesh too coarse to unload, say) is reported as failed, never silently skipped.

References
----------
Roache P. J. (1998) Verification and Validation in Computational Science and Engineering.
Hermosa, Albuquerque. Ch. 5 (grid convergence index).
Eça L., Hoekstra M. (2014) A procedure for the estimation of the numerical uncertainty of
CFD calculations based on grid refinement studies. J. Comput. Phys. 262:104-130.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from .options import mesh_check_ratios

__all__ = [
    "CheckMesh",
    "MeshCheck",
    "combined_ci95",
    "describe_mesh_check",
    "grid_convergence",
    "gci_at_size",
    "mesh_check",
]

log = logging.getLogger(__name__)
OBSERVED_ORDER = 1.6
SAFETY_FACTOR = 1.25
ANOMALOUS_SAFETY_FACTOR = 3.0
ORDER_RANGE = (0.5, 4.0)

Convergence = Literal["assumed order", "observed order", "not asymptotic"]


@dataclass(frozen=True)
class CheckMesh:
    """One check mesh of :func:`mesh_check`.

    Attributes
    ----------
    ratio : float
        Element size of the check mesh over the calibration mesh's.
    mesh_size_mm : float
    tets : int
    c1_pa : float or None
        The c1 this mesh calibrates to (one Gauss-Newton step), Pa; None if it failed.
    failure : str
        Why it failed ("" when it did not).
    """

    ratio: float
    mesh_size_mm: float
    tets: int
    c1_pa: float | None
    failure: str = ""


@dataclass(frozen=True)
class MeshCheck:
    """Result of :func:`mesh_check`.

    Attributes
    ----------
    mesh_size_mm, check_mesh_size_mm : float
        Element sizes of the calibration mesh and of the (first) check mesh.
    check_tets : int
    c1_check_pa : float or None
        The c1 the (first) check mesh calibrates to, Pa; None if it failed.
    gci_ln_c1 : float or None
        Grid convergence index of ln c1 (a 95 % bound of the discretisation error); None
        when no check mesh could be solved.
    failure : str
        Why the check failed ("" when it did not; a failed mesh of two is in ``meshes``).
    order, safety_factor : float
        The order used (assumed or observed) and the safety factor of the bound.
    convergence : {"assumed order", "observed order", "not asymptotic"}
    meshes : tuple of CheckMesh
        Every check mesh, in the order run.
    """

    mesh_size_mm: float
    check_mesh_size_mm: float
    check_tets: int
    c1_check_pa: float | None
    gci_ln_c1: float | None
    failure: str = ""
    order: float = OBSERVED_ORDER
    safety_factor: float = SAFETY_FACTOR
    convergence: Convergence = "assumed order"
    meshes: tuple[CheckMesh, ...] = ()


def grid_convergence(
    ln_c1: float, checks: list[tuple[float, float]]
) -> tuple[float, float, float, Convergence]:
    """The grid convergence index of ``ln c1`` from one or two check meshes.

    Parameters
    ----------
    ln_c1 : float
        ln c1 on the calibration mesh (c1 in Pa).
    checks : list of (ratio, ln c1)
        One check mesh, or two with reciprocal ratios (``r`` and ``1/r``).

    Returns
    -------
    gci_ln_c1, order, safety_factor : float
    convergence : str
        ``"assumed order"`` (one check), ``"observed order"`` (two, order in
        ``ORDER_RANGE``) or ``"not asymptotic"`` (two, order outside it or undefined).
    """
    if len(checks) == 1:
        ((ratio, ln_check),) = checks
        error = abs(ln_check - ln_c1) / abs(ratio**OBSERVED_ORDER - 1.0)  # Richardson
        return SAFETY_FACTOR * error, OBSERVED_ORDER, SAFETY_FACTOR, "assumed order"
    if len(checks) != 2:
        raise ValueError(f"a mesh check takes one or two check meshes, got {len(checks)}")
    mesh_check_ratios(tuple(q for q, _ in checks))  # reciprocal, each in range
    (r_a, ln_a), (r_b, ln_b) = sorted(checks, reverse=True)  # coarser first
    r = float(np.sqrt(r_a / r_b))
    e_coarse, e_fine = ln_c1 - ln_a, ln_b - ln_c1
    spread = max(ln_a, ln_b, ln_c1) - min(ln_a, ln_b, ln_c1)
    if e_fine == 0.0 and e_coarse == 0.0:
        return 0.0, float("nan"), SAFETY_FACTOR, "observed order"
    if e_fine != 0.0 and e_coarse / e_fine > 0.0:
        p = float(np.log(e_coarse / e_fine) / np.log(r))  # observed order, Roache Ch. 5
        if ORDER_RANGE[0] <= p <= ORDER_RANGE[1]:
            error = abs(e_fine) / (1.0 - r**-p)  # Richardson to the calibration mesh
            return SAFETY_FACTOR * error, p, SAFETY_FACTOR, "observed order"
    else:
        p = float("nan")  # the changes have opposite signs: oscillatory
    # Eca & Hoekstra (2014): outside the asymptotic range, 3 x the data range
    return ANOMALOUS_SAFETY_FACTOR * spread, p, ANOMALOUS_SAFETY_FACTOR, "not asymptotic"


def _check_at(cal, theta: float, ratio: float) -> CheckMesh:
    """One Gauss-Newton step of the calibration on a mesh ``ratio`` times the size."""
    import fem

    from .objective import Calibrator

    size = cal.options.mesh_size_mm * ratio  # ratio checked by mesh_check_ratios
    opts = replace(cal.options, mesh_size_mm=size)
    tets, failure = 0, ""
    try:
        check = Calibrator(cal.measurements, opts, density_kg_m3=cal.density_kg_m3)
        tets = check.mesh.n_tets
        check.fm.fixed_point_fallback = False
        check.fm.rim_fold_said = cal.fm.rim_fold_said  # said in full once per calibration
        # a check mesh solves the calibration's formulation: a GCI across straight and
        # curved stress-free elements would count their difference as discretisation error
        check.fm.spatial_fallback = False
        if cal.fm.unload_method == "spatial" and check.fm.unload_method != "spatial":
            # the calibration switched to curved stress-free elements: its check meshes
            # solve the same formulation, without the failed Newton attempt first
            check.fm.use_spatial()
        _, g = check.objective(np.array([theta]))
        step = -float(g[0]) / check.gauss_newton_curvature
    except (fem.MeshError, fem.ConvergenceError, ValueError, ZeroDivisionError) as exc:
        failure = f"{type(exc).__name__}: {exc}"
    else:
        if not np.isfinite(step):
            failure = "the Gauss-Newton step on the check mesh is not finite"
    if failure:
        log.warning("mesh check on the %.1f mm mesh failed (%s)", size, failure)
        return CheckMesh(ratio, size, tets, None, failure)
    return CheckMesh(ratio, size, tets, float(np.exp(theta + step)))


def mesh_check(
    cal, theta: float, *, ratio: float | tuple[float, ...] = 1.4, progress=None
) -> MeshCheck:
    """Re-evaluate the calibration at ``theta = ln c1`` on one or two check meshes.

    Parameters
    ----------
    cal : Calibrator
        The finished calibration (its measurements and options are reused).
    theta : float
        Calibrated ln c1 (c1 in Pa).
    ratio : float or tuple of float
        Element-size ratio of the check mesh, in [0.5, 0.9] (finer) or [1.1, 3] (coarser);
        or two reciprocal ratios (``(1.4, 1/1.4)``) for a three-mesh check with the
        observed order.
    progress : callable, optional
        Called with one line per check mesh.

    Returns
    -------
    MeshCheck
        With ``gci_ln_c1`` None when no check mesh could be solved. When one of two fails
        the other gives the bound with the assumed order (its failure in ``failure``).
    """
    ratios = mesh_check_ratios(ratio)
    size = cal.options.mesh_size_mm
    meshes = []
    for q in ratios:
        if progress is not None:
            progress(f"mesh check: the objective on a {size * q:.1f} mm mesh")
        meshes.append(_check_at(cal, theta, q))
    solved = [m for m in meshes if m.c1_pa is not None]
    failure = "; ".join(f"{m.mesh_size_mm:.1f} mm: {m.failure}" for m in meshes if m.failure)
    first = meshes[0]
    common = dict(
        mesh_size_mm=size,
        check_mesh_size_mm=first.mesh_size_mm,
        check_tets=first.tets,
        c1_check_pa=first.c1_pa,
        meshes=tuple(meshes),
    )
    if not solved:
        return MeshCheck(gci_ln_c1=None, failure=failure, **common)
    gci, order, fs, how = grid_convergence(theta, [(m.ratio, np.log(m.c1_pa)) for m in solved])
    return MeshCheck(
        gci_ln_c1=gci, failure=failure, order=order, safety_factor=fs, convergence=how, **common
    )


def describe_mesh_check(check: Mapping) -> tuple[str, str]:
    """What a mesh check found, in words: ``(meshes, convergence)``.

    Parameters
    ----------
    check : mapping
        A :class:`MeshCheck` in its JSON form (``dataclasses.asdict``, or
        ``calibration.json``'s ``uncertainty.mesh_check``; one written before ``meshes``
        was recorded describes its single check mesh).

    Returns
    -------
    meshes : str
        Each check mesh and the c1 it calibrates to, or why it failed.
    convergence : str
        ``"observed order 1.15"``, ``"assumed order 1.60"`` or ``"not asymptotic"``.
    """
    meshes = check.get("meshes") or [
        {
            "mesh_size_mm": check["check_mesh_size_mm"],
            "c1_pa": check["c1_check_pa"],
            "failure": check["failure"],
        }
    ]
    found = "; ".join(
        f"the {m['mesh_size_mm']:.1f} mm mesh "
        + (
            f"calibrates to {m['c1_pa']:.1f} Pa"
            if m["c1_pa"] is not None
            else f"failed: {m['failure']}"
        )
        for m in meshes
    )
    how = check.get("convergence", "assumed order")
    if how != "not asymptotic":
        how = f"{how} {check.get('order', OBSERVED_ORDER):.2f}"
    return found, how


def gci_at_size(check: Mapping, size_mm: float) -> float | None:
    """A mesh check's bound of ln c1 carried to a mesh of another element size.

    With ``ln c1(h) = L + C h^p`` (the module's model) the error on a mesh of size ``h'``
    is ``(h'/h)^p`` times that on the checked mesh of size ``h``, so its bound is the
    checked one times that factor; ``p`` is the check's observed order where it was in
    the asymptotic range, else the assumed :data:`OBSERVED_ORDER`. The anomalous bound of
    a check outside the range (3 x the data range) has no order of its own: it is only
    widened for a coarser mesh, never narrowed for a finer one (review AR). Review AO: a
    diagnosis that moved to the next mesh size reported a noise-only interval of c1
    (411.9-415.1 Pa on a 420 Pa set whose calibration's interval, with its bound, held the
    truth).

    Parameters
    ----------
    check : mapping
        ``calibration.json``'s ``uncertainty.mesh_check`` (or a :class:`MeshCheck` as a
        dict): ``mesh_size_mm``, ``gci_ln_c1``, ``order``, ``convergence``.
    size_mm : float
        Element size of the other mesh, mm.

    Returns
    -------
    float or None
        The bound on ln c1 there; None where the check found none.

    Raises
    ------
    ValueError
        The check gives no mesh size, or a size is not positive.
    """
    gci = check.get("gci_ln_c1")
    if gci is None:
        return None
    checked = float(check.get("mesh_size_mm") or 0.0)
    if not (checked > 0.0 and size_mm > 0.0):
        raise ValueError(
            f"a mesh bound is carried between positive mesh sizes, got {checked:g} mm (the "
            f"check's `mesh_size_mm`) and {size_mm:g} mm"
        )
    order = float(check.get("order") or OBSERVED_ORDER)
    anomalous = check.get("convergence") == "not asymptotic" or not np.isfinite(order)
    factor = (float(size_mm) / checked) ** (OBSERVED_ORDER if anomalous else order)
    return float(gci) * (max(1.0, factor) if anomalous else factor)


def combined_ci95(
    c1_pa: float, se_ln_c1: float, gci_ln_c1: float, *, critical_value: float = 1.96
) -> tuple[float, float]:
    """95 % interval of c1 from the noise (``critical_value * se``) and the GCI, in quadrature.

    ``critical_value``: the noise interval's own (the series interval's Imhof quantile;
    1.96 for a normal one).
    """
    half = float(np.hypot(critical_value * se_ln_c1, gci_ln_c1))
    return c1_pa * float(np.exp(-half)), c1_pa * float(np.exp(half))
