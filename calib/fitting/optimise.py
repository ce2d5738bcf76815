"""Gauss-Newton over ln c1 from a cheap first estimate, on a mesh with a stress-free reference.

The first estimate is the linear response to 5 % of the load (never the hardest
full-load solve at a poor guess); the stress-free reference is recovered once there,
before the optimisation, so a mesh on which none exists is found at once and the next
size tried (or the run stopped with remedies).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

import fem

from ..data.measurements import Measurements
from ..model.reference import model_mesh_notes
from .objective import Calibrator, EvaluationFailed
from .options import CalibrationOptions

__all__ = ["OptimiserStatus", "optimise", "prepare", "size_asked"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OptimiserStatus:
    """How the optimiser ended.

    Attributes
    ----------
    success : bool
        True when the step fell below its tolerance inside the bounds (a minimum).
    message : str
        Why the iteration stopped.
    iterations, evaluations : int
        Optimiser iterations and objective evaluations (each solves every calibration scan).
    failed_evaluations : int
        Evaluations whose FE solve failed.
    bound : {"lower", "upper"} or None
        The bound (x/÷ 4 around the first estimate) c1 ended on, if any.
    unsolved_c1_pa : float or None
        When the iteration stopped against a c1 that has no FE solution while the
        objective still decreased towards it (within ``EDGE_TOLERANCE``, or every trial
        of the last line search failed): that c1. The minimum of the model lies where it
        cannot be solved (a model that misses an effect of the scans, or a mesh too
        coarse for their deformation).
    unsolved_stage : {"stress-free reference", "posture"} or None
        What failed at ``unsolved_c1_pa``: the stress-free reference's recovery or a
        posture's solve (:class:`calib.fitting.objective.EvaluationFailed`).
    replaced : dict or None
        Where this fit replaced another of the same calibration (the straight
        stress-free elements' fit that stopped at such a c1, run again on curved ones,
        :func:`calib.fitting.pipeline.fit`): that fit's ``formulation``, ``c1_pa``,
        ``unsolved_c1_pa``, ``iterations``, ``evaluations``, ``failed_evaluations`` and
        ``fe_solves``; the other attributes are this fit's.
    abandoned : dict or None
        Where such a re-run on curved elements failed at its first estimate and this
        (straight) fit stands: the re-run's ``formulation``, ``reason`` and ``fe_solves``.
    """

    success: bool
    message: str
    iterations: int
    evaluations: int
    failed_evaluations: int
    bound: str | None = None
    unsolved_c1_pa: float | None = None
    unsolved_stage: str | None = None
    replaced: dict | None = None
    abandoned: dict | None = None

    @property
    def set_aside_fe_solves(self) -> int:
        """FE solves of the fits set aside: ``replaced`` and ``abandoned`` (0 where none)."""
        return sum(int((d or {}).get("fe_solves", 0)) for d in (self.replaced, self.abandoned))

    def to_json(self) -> dict:
        """The ``optimiser`` block of ``calibration.json``."""
        return {
            "success": self.success,
            "message": self.message,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "failed_evaluations": self.failed_evaluations,
            "bound": self.bound,
            "unsolved_c1_pa": self.unsolved_c1_pa,
            "unsolved_stage": self.unsolved_stage,
            "replaced": self.replaced,
            "abandoned": self.abandoned,
        }


def _start(cal: Calibrator, progress) -> float:
    """The first estimate of ln c1, with the stress-free reference recovered there."""
    c1_0 = cal.first_estimate()
    progress(f"first estimate c1 = {c1_0:.0f} Pa")
    theta0 = float(np.log(c1_0))
    _check_reference(cal, theta0, progress)
    return theta0


def size_asked(options: CalibrationOptions, size_mm: float) -> bool:
    """Whether the user chose the model mesh size ``size_mm`` (a fine mesh is then meant).

    The size the options ask for (not a retry size the calibration fell back to), when
    it is not the default or comes without retry sizes: ``--mesh-size`` sets none, so an
    explicit ``--mesh-size 12`` is asked for (review N: it was warned about as the
    default's).

    Parameters
    ----------
    options : CalibrationOptions
    size_mm : float
        The size a calibration attempt meshes with.

    Returns
    -------
    bool
    """
    default = CalibrationOptions.mesh_size_mm
    return size_mm == options.mesh_size_mm and (size_mm != default or not options.mesh_retry_mm)


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
            f"{', '.join(s.name for s in cal.calibration_scans)}"
        )
        ref = measurements.reference
        # the calibration's mesh, not the checks'; a fine mesh asked for is meant
        asked = size_asked(options, size)
        for note in model_mesh_notes(ref, cal.mesh, size, asked=asked):
            log.warning("reference scan %r: %s", ref.name, note)
        if options.objective == "nipple":
            from .profile import nipple_patches

            nipple_patches(cal)  # its interval's noise level, from measured points: no FE yet
        theta0 = _start(cal, say)
        try:  # the postures at the first estimate too (cached for the optimiser's first step)
            _evaluate(cal, theta0, say)
        except EvaluationFailed as exc:
            # review AO's independent scans: the reference recovered (curved elements) but
            # no posture solved at the first estimate, and the run ended without trying
            # the next mesh size (the clamped rim's elements change with it)
            raise fem.ConvergenceError(
                f"no FE solution of the postures on the {size:g} mm model mesh at the first "
                f"estimate c1 = {np.exp(theta0):.0f} Pa ({exc}); try another --mesh-size "
                f"(e.g. {size + 2:g}) or --reference-state shortcut"
            ) from exc
        return cal, theta0, attempts

    # each size once (review AW: calib.calibrate(..., mesh_size_mm=14) tried 14 again as
    # the default's first retry; review AY: kept in the options, replace() would lose one)
    sizes = tuple(dict.fromkeys(float(s) for s in (options.mesh_size_mm, *options.mesh_retry_mm)))
    for size in sizes[:-1]:
        try:
            return attempt(size)
        except fem.ConvergenceError as exc:
            attempts.append({"mesh_size_mm": size, "failure": str(exc)})
            what = (
                "no FE solution of the postures at the first estimate"
                if isinstance(exc.__cause__, EvaluationFailed)
                else "no stress-free reference"
            )
            say(
                f"{what} on the {size:g} mm model mesh (the clamped rim degenerates); trying "
                "the next size"
            )
    return attempt(sizes[-1])


def _check_reference(cal: Calibrator, theta0: float, progress) -> None:
    """Recover the stress-free reference at the first estimate, or stop with remedies.

    Where the inverse problem has no valid solution on the model mesh (a strongly
    sagging reference whose clamped-rim elements degenerate), no c1 nearby will do
    better: stop now, with what to change, instead of failing every evaluation.
    """
    if cal.options.reference_state == "shortcut":
        return
    progress("stress-free reference at the first estimate (inverse elastostatics)")
    try:
        cal.fm.stress_free(theta0)
        if cal.fm.unload_method == "spatial" and cal.options.reference_state == "unload":
            progress(
                "  no stress-free mesh with straight elements (slivers at the clamped rim); "
                "solved with curved ones: the reference is the prestressed loaded mesh"
            )
        # the formulation is chosen here, once: a later straight-element failure (a line
        # search's or the profile's softer c1) is a failed evaluation, not a switch that
        # would leave c1 and its interval from one model and every later output another's
        cal.fm.spatial_fallback = False
    except fem.ConvergenceError as exc:
        size = cal.options.mesh_size_mm
        raise fem.ConvergenceError(
            f"reference scan {cal.measurements.reference.name!r}: no stress-free geometry "
            f"found on the {size:g} mm model mesh at the first estimate c1 = "
            f"{np.exp(theta0):.0f} Pa ({exc}). The scan sags so far that elements at the "
            "clamped rim degenerate on this mesh; try another --mesh-size (the mesh at the "
            f"rim changes with it, e.g. {size + 2:g}), --reference-state prestress (curved "
            "stress-free elements) or --reference-state shortcut"
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


#: Armijo's sufficient-decrease constant and the line search's smallest step fraction.
ARMIJO_C = 1e-4
MIN_STEP_FRACTION = 1.0 / 64.0
#: Safeguards of the interpolated backtracking step, as fractions of the rejected one.
BACKTRACK_RANGE = (0.1, 0.5)
#: A c1 whose FE solve failed is a wall: a later step goes at most halfway to the nearest
#: one in its direction, and the iteration stops, unconverged, once a step towards it
#: would be shorter than this (ln c1: 1 % of c1, a quarter of a quick twin's 95 %
#: half-width of ~4 %) instead of bisecting the edge at ~80 s per failed solve.
EDGE_TOLERANCE = 0.01


def _nearest_failure(failed: list[float], theta: float, step: float) -> float | None:
    """The failed ln c1 nearest to ``theta`` on the side ``step`` points to, if any."""
    ahead = [f for f in failed if (f - theta) * step > 0.0]
    return min(ahead, key=lambda f: abs(f - theta)) if ahead else None


def _edge_message(unsolved_c1_pa: float) -> str:
    """Why the iteration stopped next to a c1 without an FE solution."""
    return (
        f"the objective still decreases towards c1 = {unsolved_c1_pa:.1f} Pa, where the FE "
        "model has no solution: c1 stopped at the edge of what it solves (a model that "
        "misses an effect of the scans, or a mesh too coarse for their deformation)"
    )


def _backtrack(t: float, slope: float, rise: float) -> float:
    """The next step fraction after a trial ``t`` that failed Armijo's condition.

    The minimiser of the quadratic through ``J(0)``, the slope ``J'(0) = slope`` (per unit
    step fraction, negative) and ``J(t) = J(0) + rise`` (Nocedal & Wright 2006, eq. 3.58),
    kept within ``BACKTRACK_RANGE`` of ``t``: never longer than halving, and much shorter
    when the trial overshot far (a Gauss-Newton curvature far below the true one, as for
    the nipple objective, whose residual does not vanish at the optimum).
    """
    curvature = rise - slope * t  # > 0: the trial lies above the tangent line
    t_q = -slope * t * t / (2.0 * curvature) if curvature > 0.0 else BACKTRACK_RANGE[1] * t
    return float(np.clip(t_q, BACKTRACK_RANGE[0] * t, BACKTRACK_RANGE[1] * t))


def optimise(cal: Calibrator, progress, theta0: float) -> tuple[float, float, OptimiserStatus]:
    """Minimise ``J(ln c1)`` by Gauss-Newton steps with a backtracking line search.

    The objective is a least-squares mean ``J = mean(r^2)/2`` of one parameter, with the
    exact gradient ``g = mean(r dr)`` and the Gauss-Newton curvature ``H = mean(dr^2)``
    from the direct sensitivities, so each step is ``-g/H`` (Nocedal & Wright 2006,
    ch. 10.3), clipped to the bounds ``theta0 ± ln 4``; after the first step ``H`` is the
    larger of that and the secant curvature of the last step, ``dg / d theta`` (ch. 6.1:
    Gauss-Newton leaves out ``mean(r d2r)``, which is not small where the residual does
    not vanish at the optimum, as for the nipple objective). A trial point is accepted on
    Armijo's sufficient decrease ``J(t) <= J + c t g p`` (ch. 3.1, c = 1e-4); a trial
    that does not decrease ``J`` enough shortens the step to the minimiser of the
    interpolating quadratic (eq. 3.58, within 0.1-0.5 of it, :func:`_backtrack`), and a
    trial whose FE solve fails halves it — the failure is recorded, never replaced by a
    made-up value. A c1 that failed is not tried again: later steps towards it go at most
    halfway there (a misfitting model whose minimum lies beyond what the FE model can
    solve would otherwise fail there on every iteration). The iteration stops when
    the Newton step falls below ``1e-3 / sqrt(H)`` (a change of J far below the noise:
    the criterion of the previous L-BFGS-B, ``gtol = 1e-3`` in the scaled variable), or
    ``max_iterations`` is reached, or the line search finds no acceptable point, or the
    step is held within ``EDGE_TOLERANCE`` of a failed c1 or every trial of the line
    search failed (unconverged: ``OptimiserStatus.unsolved_c1_pa``). A step shortened by
    a failed trial is never taken for convergence, however short (the full step pointed
    beyond the failure): the iteration goes on until the Gauss-Newton step itself is
    short or the edge stops it.

    Returns
    -------
    theta : float
        The calibrated ln c1 (the best point evaluated).
    objective : float
        ``J`` there (mm^2).
    status : OptimiserStatus
    """
    lo, hi = theta0 - np.log(4.0), theta0 + np.log(4.0)
    theta = theta0
    J, g = _evaluate(cal, theta, progress)  # the first estimate: its failure is fatal
    g = float(g[0])
    message, success, iterations, secant = "iteration limit reached", False, 0, 0.0
    failed: dict[float, str] = {}  # ln c1 of the trials whose FE solve failed: the stage
    unsolved = stage = None
    while iterations < cal.options.max_iterations:
        iterations += 1
        # the Gauss-Newton curvature, or the secant one of the last step where larger (a
        # residual that does not vanish at the optimum leaves Gauss-Newton too flat)
        H = max(cal.gauss_newton_curvature, secant, 1e-300)
        tol = 1e-3 / np.sqrt(H)
        step = float(np.clip(theta - g / H, lo, hi)) - theta
        if abs(step) < tol:
            message, success = "the Gauss-Newton step is below the tolerance", True
            break
        wall, capped = _nearest_failure(list(failed), theta, step), False
        if wall is not None and abs(step) > 0.5 * abs(wall - theta):
            if 0.5 * abs(wall - theta) < EDGE_TOLERANCE:
                unsolved, stage = float(np.exp(wall)), failed[wall]
                message = _edge_message(unsolved)
                log.warning("c1 stopped at %.1f Pa, next to an unsolvable c1", np.exp(theta))
                break
            step, capped = 0.5 * (wall - theta), True
        accepted, t, any_failed, any_solved = None, 1.0, False, False
        while t >= MIN_STEP_FRACTION:
            trial = theta + t * step
            try:
                Jt, gt = _evaluate(cal, trial, progress)
            except EvaluationFailed as exc:
                failed[trial], any_failed = exc.stage, True
                progress(f"  no FE solution at c1 = {np.exp(trial):.1f} Pa: step halved")
                t /= 2.0
                continue
            any_solved = True
            if Jt <= J + ARMIJO_C * t * step * g:
                accepted = (trial, Jt, float(gt[0]))
                break
            t = _backtrack(t, step * g, Jt - J)
        if accepted is None:
            if not any_solved:  # every trial failed: the edge lies within the last one
                unsolved, stage = float(np.exp(trial)), failed[trial]
                message = _edge_message(unsolved)
                log.warning("c1 stopped at %.1f Pa, next to an unsolvable c1", np.exp(theta))
            else:
                message = "the line search found no point that decreases J along the step"
            break
        secant = (accepted[2] - g) / (accepted[0] - theta)  # dg/dtheta along the step
        theta, J, g = accepted
        # a capped step, or one a failed trial shortened, says nothing of a minimum
        if abs(t * step) < tol and not capped and not any_failed:
            message, success = "the step taken is below the tolerance", True
            break
    side = None
    for name, b in (("lower", lo), ("upper", hi)):
        if abs(theta - b) < 1e-9 and (g > 0 if name == "lower" else g < 0):
            side = name
            success = False
            around = np.exp(theta0)
            hint = "; the first estimate was --c1-guess" if cal.first_estimate_from_guess else ""
            message = (
                f"c1 reached the {name} bound of its search range (x/÷ 4 around "
                f"{around:.0f} Pa{hint})"
            )
            log.warning(
                "c1 ended on the %s bound (%.0f Pa): the estimate may be poor", name, np.exp(theta)
            )
    status = OptimiserStatus(
        success=success,
        message=message,
        iterations=iterations,
        evaluations=len(cal.history),
        failed_evaluations=sum(1 for h in cal.history if h.get("failed")),
        bound=side,
        unsolved_c1_pa=unsolved,
        unsolved_stage=stage,
    )
    return theta, J, status
