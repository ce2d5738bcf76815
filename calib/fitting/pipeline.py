"""``fit``: the calibration of c1 as a pure function, measurements in, a Calibration out.

No files are written and nothing is printed: progress goes to the ``progress``
callback (or the ``calib.fitting`` logger at INFO). The steps are those of the README's
"calib: the calibration": first estimate and stress-free reference
(:mod:`calib.fitting.optimise`), Gauss-Newton, the 95 % interval (surface: the
series interval under the residuals' variogram noise model with the mesh check's GCI,
and the misfit test, :func:`calib.fitting.uncertainty.series_uncertainty`; landmarks:
Gauss-Newton; nipple: the likelihood profile) and the likelihood profile over c1.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, replace

import numpy as np

from ..data.measurements import Measurements
from ..data.session import SessionError, checked_density_kg_m3
from ..model.reference import body_height_mm, scale_of
from ..model.residuals import surface_area_mm2
from ..stats.intervals import MIN_SERIES_POINTS
from ..stats.noise import SMOOTH_TAKEN_FOR_NOISE
from .meshcheck import MeshCheck, combined_ci95, describe_mesh_check, mesh_check
from .objective import Calibrator, EvaluationFailed
from .optimise import OptimiserStatus, optimise, prepare
from .options import CalibrationOptions, mesh_check_ratios
from .profile import likelihood_profile, nipple_interval, profile_rows
from .result import Calibration, phantom_frame
from .uncertainty import (
    GAUSS_NEWTON_COVERAGE,
    Uncertainty,
    gauss_newton_uncertainty,
    series_uncertainty,
)

__all__ = ["fit"]

log = logging.getLogger(__name__)


def _nipple_uncertainty(cal: Calibrator, theta: float, r: np.ndarray, say):
    """The nipple objective's interval from its likelihood profile; no mesh check.

    The mesh check's Gauss-Newton step needs the residual's derivative, which is about
    zero at the nipple objective's optimum (see :mod:`calib.fitting.profile`).
    """
    say("95 % interval from the likelihood profile of the nipple error")
    unc, prof = nipple_interval(cal, theta, r)
    say(
        f"  noise {unc.residual_sd_mm:.3f} mm (surface near the nipple), "
        f"{prof.evaluations} evaluations"
    )
    say(
        "mesh check: not run for the nipple objective (its residual is flat in c1 at the "
        "optimum, so a Gauss-Newton step on another mesh is meaningless)"
    )
    return unc, None, unc.c1_ci95_pa, profile_rows(prof, len(r)), None


def _mesh_check(cal: Calibrator, theta: float, unc: Uncertainty, say):
    """The mesh check (a coarser one falls back to a finer mesh) and the combined interval."""
    o = cal.options
    ratios = mesh_check_ratios(o.mesh_check_ratio)
    if not ratios or unc.se_ln_c1 is None:
        return None, unc.c1_ci95_pa
    check = mesh_check(cal, theta, ratio=ratios, progress=say)
    if check.gci_ln_c1 is None and len(ratios) == 1 and ratios[0] > 1.0:
        finer = 1.0 / ratios[0]
        say(
            f"mesh check on the coarser mesh failed ({check.failure}); checking on a "
            f"{o.mesh_size_mm * finer:.1f} mm mesh instead"
        )
        check = mesh_check(cal, theta, ratio=finer, progress=say)
    if check.gci_ln_c1 is None:
        say(f"mesh check failed ({check.failure}): the interval reflects noise only")
        return check, unc.c1_ci95_pa
    say(_mesh_check_line(check))
    crit = unc.interval["critical_value"] if unc.interval else 1.96
    ci = combined_ci95(float(np.exp(theta)), unc.se_ln_c1, check.gci_ln_c1, critical_value=crit)
    return check, ci


def _mesh_check_line(check: MeshCheck) -> str:
    """What the mesh check found, in one progress line."""
    found, how = describe_mesh_check(asdict(check))
    if how == "not asymptotic":
        how = "not in the asymptotic range (3 x the spread of c1 over the meshes)"
    return f"mesh check: {found}; {how}; GCI {100 * check.gci_ln_c1:.2g} % of c1"


def _measured_area_mm2(cal: Calibrator) -> float:
    """Area of the calibration scans' measured surfaces off the back plate, mm^2."""
    total = 0.0
    for s in cal.calibration_scans:
        total += surface_area_mm2(s.vertices_mm, s.faces[s.scored[s.faces].any(axis=1)])
    return total


def _curved_may_go_further(cal: Calibrator, status: OptimiserStatus) -> bool:
    """Whether the fit stopped where straight stress-free elements have no solution.

    ``--reference-state unload`` chooses its formulation at the first estimate (straight
    where that c1 admits them); where the objective still decreased towards a c1 whose
    straight recovery failed (not a posture's solve), the curved elements of the
    prestressed loaded mesh may solve it (the quick skin twin of seed 1: straight
    elements stopped at 602 Pa, its calibration of 2026-12-01 switched and found
    544.6 Pa).
    """
    return (
        status.unsolved_c1_pa is not None
        and status.unsolved_stage == "stress-free reference"
        and cal.options.reference_state == "unload"
        and cal.fm.unload_method == "newton"
    )


def _again_curved(cal: Calibrator, theta0: float, straight: tuple, say):
    """The whole fit again with curved stress-free elements from the first estimate.

    On a new calibrator (:meth:`Calibrator.curved`): one formulation for c1, its
    interval and every saved state; the straight fit is recorded in the status
    (``replaced``, and its end in the message). Where the curved elements have no
    solution at the first estimate either, the straight fit stands, said.

    Returns
    -------
    cal, theta, value, status
        The calibrator and the fit that stand.
    """
    theta_s, value_s, status_s = straight
    edge = status_s.unsolved_c1_pa
    why = (
        f"straight stress-free elements have no solution at c1 = {edge:.1f} Pa, where the "
        "objective still decreases: the fit again with curved ones (the prestressed loaded "
        "mesh) from the first estimate"
    )
    say(why)
    log.warning(why)
    replaced = {
        "formulation": "straight stress-free elements",
        "c1_pa": float(np.exp(theta_s)),
        "unsolved_c1_pa": edge,
        "iterations": status_s.iterations,
        "evaluations": status_s.evaluations,
        "failed_evaluations": status_s.failed_evaluations,
        "fe_solves": int(cal.fm.solves),
    }
    curved = cal.curved()
    try:
        theta, value, status = optimise(curved, say, theta0)
    except EvaluationFailed as exc:  # at the first estimate, its failure fatal there
        stands = (
            f"curved stress-free elements failed at the first estimate too ({exc}): the "
            f"straight fit stands, stopped at c1 = {np.exp(theta_s):.1f} Pa"
        )
        say(stands)
        log.warning(stands)
        why = f"curved stress-free elements tried again from the first estimate: {exc}"
        abandoned = {
            "formulation": "curved stress-free elements",
            "reason": str(exc),
            "fe_solves": int(curved.fm.solves),
        }
        message = f"{status_s.message} ({why})"
        return cal, theta_s, value_s, replace(status_s, message=message, abandoned=abandoned)
    why = (
        f"curved stress-free elements, after straight ones stopped at {edge:.1f} Pa "
        f"({status_s.evaluations} evaluations)"
    )
    status = replace(status, message=f"{status.message} ({why})", replaced=replaced)
    return curved, theta, value, status


def _uncertainty(cal: Calibrator, theta: float, say):
    """Interval, mesh check and likelihood profile at the calibrated ``theta``."""
    final = cal.residuals(theta, cal.calibration_scans, gradient=True)
    r = np.concatenate([v.r for v in final.values()])
    if cal.options.objective == "nipple":
        return _nipple_uncertainty(cal, theta, r, say)
    dr = np.concatenate([v.dr for v in final.values()])
    pts = np.concatenate([v.points_mm for v in final.values()])
    c1, model_fit, unc = float(np.exp(theta)), None, None
    if cal.options.objective == "surface" and len(r) < MIN_SERIES_POINTS:
        # review AJ: this fallback was silent (its coverage: README, "Measured coverage")
        why = (
            f"{len(r)} surface residuals, under the {MIN_SERIES_POINTS} the series interval "
            "needs: the Gauss-Newton interval with an effective sample count instead "
            f"(uncertainty.method; {GAUSS_NEWTON_COVERAGE}), and no model-misfit test"
        )
        say(why)
        log.warning(why)
    elif cal.options.objective == "surface":
        from ..stats.intervals import IntervalError
        from ..stats.noise import MAX_LAG_MM, NoiseModelError

        labels = np.concatenate([np.full(len(v.r), i) for i, v in enumerate(final.values())])
        try:
            # review BN N4: the variogram's reach scales with the body, as the diagnosis'
            reach = MAX_LAG_MM * scale_of(cal.measurements.reference)
            unc, fit_test = series_uncertainty(
                c1, r, dr, pts, labels, seed=cal.options.seed, max_lag_mm=reach
            )
        except (NoiseModelError, IntervalError) as exc:
            # after the whole fit: say it and keep the run, with the interval that needs
            # no noise model (no misfit test then)
            why = (
                f"the series interval failed ({exc}): the Gauss-Newton interval with an "
                "effective sample count instead (uncertainty.method), and no model-misfit test"
            )
            say(why)
            log.warning(why)
        else:
            model_fit = fit_test.as_json()
            say(_model_fit_line(fit_test))
    if unc is None:
        area = _measured_area_mm2(cal) if cal.options.objective == "surface" else None
        unc = gauss_newton_uncertainty(c1, r, dr, pts, area_mm2=area)
    check, ci95 = _mesh_check(cal, theta, unc, say)
    if cal.options.profile_points >= 2:
        say(
            f"likelihood profile over c1: {cal.options.profile_points} points (a check of "
            "the interval's shape, calibration.json's profile; --profile 0 skips it)"
        )
    profile = likelihood_profile(cal, theta, unc.se_ln_c1, unc.n_effective, say=say)
    return unc, check, ci95, profile, model_fit


#: Said with a ``fits`` verdict whose noise model's correlation length ended on its bound.
LENGTH_AT_BOUND_NOTE = (
    "but the noise model's correlation length ended at its search bound (the residual "
    f"does not level off across the phantom): {SMOOTH_TAKEN_FOR_NOISE}"
)


def _model_fit_line(fit) -> str:
    """The misfit test's verdict in one progress line."""
    if fit.verdict == "fits":
        line = (
            f"model fit: no large-scale structure beyond the noise (band-F p = {fit.p_value:.2g}"
            f" >= {fit.alpha:g})"
        )
        return line + (f"; {LENGTH_AT_BOUND_NOTE}" if fit.noise.length_at_bound else "")
    return (
        f"MODEL MISFIT: the residual holds large-scale structure the noise cannot explain "
        f"(band-F p = {fit.p_value:.2g} < {fit.alpha:g}); the interval covers noise and mesh, "
        "not this model error (phantom-calib diagnose looks for the missing effect)"
    )


def _density(measurements: Measurements, density_kg_m3: float | None) -> float:
    """The density a fit takes, kg/m^3: the one given, else the measurements'.

    Review AI: a default of 1000 kg/m^3 took the place of a session's 1050 (c1 5 % off).
    """
    density = measurements.density_kg_m3 if density_kg_m3 is None else density_kg_m3
    if density is None:
        raise SessionError(
            "no phantom density: these measurements carry none (not from "
            "calib.data.load_measurements); pass density_kg_m3 (kg/m^3)"
        )
    return checked_density_kg_m3(density, "density_kg_m3")


def fit(
    measurements: Measurements,
    options: CalibrationOptions | None = None,
    *,
    density_kg_m3: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> Calibration:
    """Calibrate c1 on the calibration scans of a session.

    Parameters
    ----------
    measurements : Measurements
        Every scan after ingest (:func:`calib.data.load_measurements`), reference frame.
    options : CalibrationOptions, optional
        Defaults to ``CalibrationOptions()`` (surface objective, unload, 12 mm mesh).
    density_kg_m3 : float, optional
        Phantom density, kg/m^3; default the measurements' (the session's
        ``phantom.density_kg_m3``). Under gravity alone c1 scales with it.
    progress : callable, optional
        Called with a line of text at every step and FE evaluation.

    Returns
    -------
    Calibration

    Raises
    ------
    TypeError
        ``measurements`` not :class:`Measurements` or ``options`` not
        :class:`CalibrationOptions`.
    calib.data.session.SessionError
        No density (neither given nor in the measurements); no scan with role
        ``calibration`` (a ``ValueError``).
    ValueError
        A density outside :data:`calib.data.session.DENSITY_RANGE_KG_M3`;
        no scan whose gravity defines the phantom
        frame's axes (:func:`calib.fitting.result.phantom_frame`), said before any FE work;
        for the ``nipple`` objective, a calibration scan with too few measured points near
        its nipple for the interval's noise level, said before any FE work.
    fem.ConvergenceError
        No stress-free reference on any model mesh tried.
    """
    if not (hasattr(measurements, "scans") and hasattr(measurements, "reference")):
        # review AU: a path gave an AttributeError from inside (duck-typed: tests and
        # callers pass their own containers of scans)
        raise TypeError(
            "fit takes the Measurements of calib.load_measurements(work, session), got "
            f"{type(measurements).__name__}; from a scan folder: calib.calibrate(scans, work)"
        )
    if not isinstance(options, (CalibrationOptions, type(None))):
        raise TypeError(f"options must be a CalibrationOptions, got {type(options).__name__}")
    options = options or CalibrationOptions()
    density_kg_m3 = _density(measurements, density_kg_m3)
    say = progress or log.info
    t0 = time.perf_counter()
    phantom_frame(measurements.reference, measurements.scans.values())  # fails before the FE
    cal, theta0, failed_sizes = prepare(measurements, options, density_kg_m3, say)
    theta, value, status = optimise(cal, say, theta0)
    if _curved_may_go_further(cal, status):
        cal, theta, value, status = _again_curved(cal, theta0, (theta, value, status), say)
    before = status.set_aside_fe_solves  # the replaced or abandoned fit's
    cal.fm.keep_recovery(theta)  # solved again after the profile (below): keep it
    c1 = float(np.exp(theta))
    aside = "the straight fit" if status.replaced else "the curved attempt"
    also = f", {before} of them in {aside}" if before else ""
    say(
        f"c1 = {c1:.1f} Pa after {status.iterations} iterations "
        f"({before + cal.fm.solves} FE solves so far{also}; the interval, mesh check and "
        "final states add theirs)"
    )
    unc, check, ci95, profile, model_fit = _uncertainty(cal, theta, say)
    cal.fm.stress_free(theta)  # the calibrated c1's geometry again (the profile moved it)
    o = cal.options
    return Calibration(
        c1_pa=c1,
        c1_ci95_pa=None if ci95 is None else (float(ci95[0]), float(ci95[1])),
        objective=o.objective,
        objective_value_mm2=value,
        reference_state=o.reference_state,
        uncertainty=unc,
        model_fit=model_fit,
        mesh_check=check if isinstance(check, MeshCheck) else None,
        optimiser=status,
        history=tuple(cal.history),
        profile=tuple(profile),
        mesh={
            "n_tets": cal.mesh.n_tets,
            "n_nodes": cal.mesh.n_nodes,
            "size_mm": o.mesh_size_mm,
            "failed_sizes": failed_sizes,
            # review BN: a body few elements tall is a caveat (calibration_caveats)
            "height_mm": (height := body_height_mm(cal.measurements.reference, cal.mesh)),
            "elements_in_height": height / o.mesh_size_mm,
            "formulation": o.formulation,
            "support": cal.support.as_dict(),
        },
        reference_recovery={
            "method": "none (shortcut)"
            if o.reference_state == "shortcut"
            else cal.fm.unload_method,
            "inverted_elements": cal.fm.inverted_reference_elements,
        },
        fe_solves=int(before + cal.fm.solves),
        wall_s=time.perf_counter() - t0,
        options=o,
        density_kg_m3=density_kg_m3,
        calibrator=cal,
    )
