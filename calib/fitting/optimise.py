"""L-BFGS-B over ln c1 from a cheap first estimate, on a mesh with a stress-free reference.

The first estimate is the linear response to 5 % of the load (never the hardest
full-load solve at a poor guess); the stress-free reference is recovered once there,
before the optimisation, so a mesh on which none exists is found at once and the next
size tried (or the run stopped with remedies).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

import fem

from ..data.measurements import Measurements
from .objective import Calibrator
from .options import CalibrationOptions

__all__ = ["OptimiserStatus", "optimise", "prepare"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OptimiserStatus:
    """How the optimiser ended.

    Attributes
    ----------
    success : bool
        scipy's ``success`` flag (a converged minimum within the iteration limit).
    message : str
        scipy's message.
    iterations, evaluations : int
        Optimiser iterations and objective evaluations (each solves every calibration scan).
    failed_evaluations : int
        Evaluations whose FE solve failed.
    bound : {"lower", "upper"} or None
        The bound (x/÷ 4 around the first estimate) c1 ended on, if any.
    """

    success: bool
    message: str
    iterations: int
    evaluations: int
    failed_evaluations: int
    bound: str | None = None

    def to_json(self) -> dict:
        """The ``optimiser`` block of ``calibration.json``."""
        return {
            "success": self.success,
            "message": self.message,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "failed_evaluations": self.failed_evaluations,
            "bound": self.bound,
        }


def _start(cal: Calibrator, progress) -> float:
    """The first estimate of ln c1, with the stress-free reference recovered there."""
    c1_0 = cal.first_estimate()
    progress(f"first estimate c1 = {c1_0:.0f} Pa")
    theta0 = float(np.log(c1_0))
    _check_reference(cal, theta0, progress)
    return theta0


def prepare(
    measurements: Measurements, options: CalibrationOptions, density_kg_m3: float, say
) -> tuple[Calibrator, float, list[dict]]:
    """A calibrator whose model mesh admits a stress-free reference at the first estimate.

    Tries ``mesh_size_mm`` and then each of ``mesh_retry_mm``; every attempt that fails
    is reported and recorded, the last one's error is raised.

    Returns
    -------
    calibrator : Calibrator
    theta0 : float
        The first estimate of ln c1.
    failed_sizes : list of dict
        ``{"mesh_size_mm", "failure"}`` of each size tried before the one used.
    """
    attempts: list[dict] = []

    def attempt(size: float):
        cal = Calibrator(
            measurements,
            replace(options, mesh_size_mm=size, mesh_retry_mm=()),
            density_kg_m3=density_kg_m3,
        )
        say(
            f"reference mesh: {cal.mesh.n_tets} tets ({size:g} mm); calibration scans: "
            f"{[s.name for s in cal.calibration_scans]}"
        )
        return cal, _start(cal, say), attempts

    sizes = (options.mesh_size_mm, *options.mesh_retry_mm)
    for size in sizes[:-1]:
        try:
            return attempt(size)
        except fem.ConvergenceError as exc:
            attempts.append({"mesh_size_mm": size, "failure": str(exc)})
            say(
                f"no stress-free reference on the {size:g} mm model mesh (the clamped rim "
                "degenerates); trying the next size"
            )
    return attempt(sizes[-1])


def _check_reference(cal: Calibrator, theta0: float, progress) -> None:
    """Recover the stress-free reference at the first estimate, or stop with remedies.

    Where the inverse problem has no valid solution on the model mesh (a strongly
    sagging reference whose clamped-rim elements degenerate), no c1 nearby will do
    better: stop now, with what to change, instead of failing every evaluation.
    """
    if cal.options.reference_state != "unload":
        return
    progress("stress-free reference at the first estimate (inverse elastostatics)")
    try:
        cal.fm.stress_free(theta0)
    except fem.ConvergenceError as exc:
        size = cal.options.mesh_size_mm
        raise fem.ConvergenceError(
            f"reference scan {cal.measurements.reference.name!r}: no stress-free geometry "
            f"found on the {size:g} mm model mesh at the first estimate c1 = "
            f"{np.exp(theta0):.0f} Pa ({exc}). The scan sags so far that elements at the "
            "clamped rim degenerate on this mesh; try another --mesh-size (the mesh at the "
            f"rim changes with it, e.g. {size + 2:g}) or --reference-state shortcut"
        ) from exc


def _evaluate(cal: Calibrator, theta: float, progress) -> tuple[float, np.ndarray]:
    """The objective at theta, with a progress line for every new FE evaluation."""
    n = len(cal.history)
    J, g = cal.objective(np.array([theta]))
    if len(cal.history) > n:
        h = cal.history[-1]
        state = "failed" if h.get("failed") else f"rms {h['rms_mm']:.3f} mm, {h['wall_s']:.0f} s"
        progress(f"evaluation {len(cal.history)}: c1 = {h['c1_pa']:.1f} Pa, {state}")
    return J, g


def optimise(cal: Calibrator, progress, theta0: float) -> tuple[float, float, OptimiserStatus]:
    """L-BFGS-B over ln c1, rescaled by the Gauss-Newton curvature at the first estimate.

    With ``z = s (theta - theta0)`` and ``s^2`` the curvature, the objective's Hessian in
    ``z`` is about 1, so the optimiser's first trial step is well sized, and ``gtol`` in
    ``z`` (1e-3) stops it once the Newton step in ln c1 is below about 1e-3 / s.

    Returns
    -------
    theta : float
        The calibrated ln c1.
    objective : float
        ``J`` there (mm^2).
    status : OptimiserStatus
    """
    _evaluate(cal, theta0, progress)
    s = float(np.sqrt(max(cal.gauss_newton_curvature, 1e-12)))

    def f(z):
        J, g = _evaluate(cal, theta0 + float(z[0]) / s, progress)
        return J, g / s

    bound = np.log(4.0) * s
    res = minimize(
        f,
        [0.0],
        jac=True,
        method="L-BFGS-B",
        bounds=[(-bound, bound)],
        options={"maxiter": cal.options.max_iterations, "ftol": 1e-9, "gtol": 1e-3},
    )
    theta = theta0 + float(res.x[0]) / s
    side = None
    if abs(float(res.x[0])) >= 0.999 * bound:
        side = "upper" if res.x[0] > 0 else "lower"
        log.warning(
            "c1 ended on the %s bound (%.0f Pa): the estimate may be poor", side, np.exp(theta)
        )
    status = OptimiserStatus(
        success=bool(res.success),
        message=str(res.message),
        iterations=int(res.nit),
        evaluations=len(cal.history),
        failed_evaluations=sum(1 for h in cal.history if h.get("failed")),
        bound=side,
    )
    return theta, float(res.fun), status
