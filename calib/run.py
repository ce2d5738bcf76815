"""``phantom-calib calibrate``: ingest (when needed), calibrate, report."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

import fem

from .calibrate import CalibrationOptions, Calibrator
from .io import provenance, write_json_atomic
from .measurements import load_measurements
from .meshcheck import combined_ci95, mesh_check
from .nipple_interval import nipple_interval, profile_rows
from .report import write_error_ply, write_error_png
from .session import load_session
from .uncertainty import gauss_newton_uncertainty

__all__ = ["run_calibration"]

log = logging.getLogger(__name__)


def _summary(s) -> dict:
    return {"mean": s.mean_mm, "sd": s.sd_mm, "median": s.median_mm, "p95": s.p95_mm,
            "max": s.max_mm, "n": s.n}  # fmt: skip


def _scan_metrics(cal: Calibrator, scan, st, work: Path, c1: float) -> dict:
    import registration

    pos, faces = st.positions_mm, cal.sim.faces
    pts = scan.vertices_mm[~scan.back_plate]
    icp = registration.icp_refine(pts, pos[np.unique(faces)])
    T = icp.T_target_from_source
    surf = registration.surface_errors(pts, pos, faces, frames=("fiducial", "icp"), T_icp=T)
    nip = int(cal.mesh.node_set("nipple")[0])
    nipple = registration.nipple_error(pos[nip], scan.vertices_mm, frames=("fiducial", "icp"),
                                       T_icp=np.linalg.inv(T))  # fmt: skip
    out = {
        "role": scan.role,
        "gravity_ref": scan.gravity_ref.tolist(),
        "nipple_error_mm": {f: e.error_mm for f, e in nipple.items()},
        "nipple_landmark_error_mm": {"fiducial": float(np.linalg.norm(pos[nip] - scan.nipple_mm))},
        "surface_error_mm": {f: _summary(e.summary) for f, e in surf.items()},
        "icp": {"fitness": icp.fitness, "inlier_rmse_mm": icp.inlier_rmse_mm},
    }
    tumour = cal._tumour(st, gradient=False)
    if tumour is not None and scan.tumour_mm is not None:
        p_icp = np.linalg.inv(T)[:3, :3] @ tumour[0] + np.linalg.inv(T)[:3, 3]
        out["tumour_error_mm"] = {"fiducial": float(np.linalg.norm(tumour[0] - scan.tumour_mm)),
                                  "icp": float(np.linalg.norm(p_icp - scan.tumour_mm))}  # fmt: skip
    err = surf["fiducial"].distances_mm
    folder = work / "calibration"
    write_error_ply(folder / f"{scan.name}_error.ply", scan.vertices_mm, scan.faces,
                    _per_vertex(scan, err))  # fmt: skip
    write_error_png(folder / f"{scan.name}_error.png", pts, err,
                    f"{scan.name}: c1 = {c1:.0f} Pa, fiducial frame, mean |e| = "
                    f"{np.mean(np.abs(err)):.2f} mm")  # fmt: skip
    _write_vtu(folder / f"{scan.name}_deformed.vtu", cal, pos)
    out["files"] = [f"calibration/{scan.name}_error.ply", f"calibration/{scan.name}_error.png",
                    f"calibration/{scan.name}_deformed.vtu"]  # fmt: skip
    return out


def _final_scan(cal: Calibrator, scan, theta: float, work: Path) -> dict:
    """Errors and maps of one scan at the calibrated c1; a failed solve is reported."""
    try:
        st = cal.fm.evaluate(theta, {scan.name: scan.gravity_ref}, gradient=False)[scan.name]
    except fem.ConvergenceError as exc:
        log.warning("scan %s: no FE solution at the calibrated c1 (%s)", scan.name, exc)
        return {"role": scan.role, "gravity_ref": scan.gravity_ref.tolist(), "failed": str(exc)}
    return _scan_metrics(cal, scan, st, work, float(np.exp(theta)))


def _per_vertex(scan, err_off_back: np.ndarray) -> np.ndarray:
    e = np.zeros(len(scan.vertices_mm))
    e[~scan.back_plate] = err_off_back
    return e


def _write_vtu(path: Path, cal: Calibrator, positions: np.ndarray) -> None:
    from fem.io import write_mesh

    X = cal.fm._X
    write_mesh(cal.mesh.with_nodes(positions), path, point_data={"displacement_mm": positions - X})


def _write_reference_mesh(path: Path, cal: Calibrator) -> None:
    """The model's stress-free mesh at the calibrated c1 (reference frame, mm)."""
    from fem.io import write_mesh

    write_mesh(cal.mesh.with_nodes(cal.fm._X), path)


def _start(cal: Calibrator, progress) -> float:
    """The first estimate of ln c1, with the stress-free reference recovered there."""
    c1_0 = cal.first_estimate()
    progress(f"first estimate c1 = {c1_0:.0f} Pa")
    theta0 = float(np.log(c1_0))
    _check_reference(cal, theta0, progress)
    return theta0


def _calibrator(meas, options: CalibrationOptions, density: float, say):
    """A calibrator whose model mesh admits a stress-free reference at the first estimate.

    Tries ``mesh_size_mm`` and then each of ``mesh_retry_mm``; every attempt that fails
    is reported and recorded, the last one's error is raised. Returns
    ``(calibrator, theta0, failed_attempts)``.
    """
    attempts: list[dict] = []

    def attempt(size: float):
        cal = Calibrator(meas, replace(options, mesh_size_mm=size, mesh_retry_mm=()),
                         density_kg_m3=density)  # fmt: skip
        say(f"reference mesh: {cal.mesh.n_tets} tets ({size:g} mm); calibration scans: "
            f"{[s.name for s in cal.calibration_scans]}")  # fmt: skip
        return cal, _start(cal, say), attempts

    sizes = (options.mesh_size_mm, *options.mesh_retry_mm)
    for size in sizes[:-1]:
        try:
            return attempt(size)
        except fem.ConvergenceError as exc:
            attempts.append({"mesh_size_mm": size, "failure": str(exc)})
            say(f"no stress-free reference on the {size:g} mm model mesh (the clamped rim "
                "degenerates); trying the next size")  # fmt: skip
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


def _optimise(cal: Calibrator, progress, theta0: float | None = None) -> tuple[float, object]:
    """L-BFGS-B over ln c1, rescaled by the Gauss-Newton curvature at the first estimate.

    With ``z = s (theta - theta0)`` and ``s^2`` the curvature, the objective's Hessian in
    ``z`` is about 1, so the optimiser's first trial step is well sized, and ``gtol`` in
    ``z`` (1e-3) stops it once the Newton step in ln c1 is below about 1e-3 / s.
    """
    if theta0 is None:
        theta0 = _start(cal, progress)
    _evaluate(cal, theta0, progress)
    s = float(np.sqrt(max(cal.gauss_newton_curvature, 1e-12)))

    def f(z):
        J, g = _evaluate(cal, theta0 + float(z[0]) / s, progress)
        return J, g / s

    bound = np.log(4.0) * s
    res = minimize(f, [0.0], jac=True, method="L-BFGS-B", bounds=[(-bound, bound)],
                   options={"maxiter": cal.options.max_iterations, "ftol": 1e-9,
                            "gtol": 1e-3})  # fmt: skip
    theta = theta0 + float(res.x[0]) / s
    if abs(float(res.x[0])) >= 0.999 * bound:
        log.warning("c1 ended on a bound (%.0f Pa): the estimate may be poor", np.exp(theta))
    return theta, res


def _profile(cal: Calibrator, theta: float, se: float | None, n_eff: float) -> list[dict]:
    k = cal.options.profile_points
    if k < 2:
        return []
    half = max(2.0 * se, 0.05) if se is not None and np.isfinite(se) else 0.2
    rows = [_profile_point(cal, float(t)) for t in np.linspace(theta - half, theta + half, k)]
    jmin = min((row["objective"] for row in rows if not row.get("failed")), default=None)
    for row in rows:
        if not row.get("failed"):
            row["minus2_delta_loglik"] = float(n_eff * np.log(row["objective"] / jmin))
    return rows


def _profile_point(cal: Calibrator, theta: float) -> dict:
    """One profile row; a point whose FE solve fails is recorded as failed, not fatal."""
    try:
        res = cal.residuals(theta, cal.calibration_scans, gradient=False, retry=False)
    except fem.ConvergenceError as exc:
        log.warning("likelihood profile: FE failed at c1=%.1f Pa (%s)", np.exp(theta), exc)
        return {"c1_pa": float(np.exp(theta)), "objective": None, "failed": True}
    r = np.concatenate([v.r for v in res.values()])
    return {"c1_pa": float(np.exp(theta)), "objective": 0.5 * float(np.mean(r**2))}


def _nipple_uncertainty(cal: Calibrator, theta: float, r: np.ndarray, say):
    """The nipple objective's interval from its likelihood profile; no mesh check.

    The mesh check's Gauss-Newton step needs the residual's derivative, which is about
    zero at the nipple objective's optimum (see :mod:`calib.nipple_interval`).
    """
    say("95 % interval from the likelihood profile of the nipple error")
    unc, prof = nipple_interval(cal, theta, r)
    say(f"  noise {unc.residual_sd_mm:.3f} mm (surface near the nipple), "
        f"{prof.evaluations} evaluations")  # fmt: skip
    say("mesh check: not run for the nipple objective (its residual is flat in c1 at the "
        "optimum, so a Gauss-Newton step on another mesh is meaningless)")  # fmt: skip
    return unc, None, unc.c1_ci95_pa, profile_rows(prof, len(r))


def _mesh_check(cal: Calibrator, theta: float, unc, say):
    """The mesh check (coarser, then finer if that fails) and the combined 95 % interval."""
    o = cal.options
    if not o.mesh_check_ratio or unc.se_ln_c1 is None:
        return None, unc.c1_ci95_pa
    say(f"mesh check: the objective on a {o.mesh_size_mm * o.mesh_check_ratio:.1f} mm mesh")
    check = mesh_check(cal, theta, ratio=o.mesh_check_ratio)
    if check.gci_ln_c1 is None and o.mesh_check_ratio > 1.0:
        finer = 1.0 / o.mesh_check_ratio
        say(f"mesh check on the coarser mesh failed ({check.failure}); checking on a "
            f"{o.mesh_size_mm * finer:.1f} mm mesh instead")  # fmt: skip
        check = mesh_check(cal, theta, ratio=finer)
    if check.gci_ln_c1 is None:
        say(f"mesh check failed ({check.failure}): the interval reflects noise only")
        return check, unc.c1_ci95_pa
    return check, combined_ci95(float(np.exp(theta)), unc.se_ln_c1, check.gci_ln_c1)


def run_calibration(scans_dir, work, options: CalibrationOptions, *, progress=None) -> dict:
    """Calibrate c1 on a scan session and write ``WORK/calibration.json`` and maps."""
    say = progress or (lambda msg: log.info(msg))
    t0 = time.perf_counter()
    work = Path(work)
    session = load_session(scans_dir)
    if not all((work / "scans" / s.name / "ingest.json").is_file() for s in session.scans):
        from .ingest import ingest_session

        say("ingesting scans")
        ingest_session(scans_dir, work)
    meas = load_measurements(work, session)
    cal, theta0, attempts = _calibrator(meas, options, session.density_kg_m3, say)
    options = cal.options
    theta, res = _optimise(cal, say, theta0)
    c1 = float(np.exp(theta))
    say(f"c1 = {c1:.1f} Pa after {res.nit} iterations ({cal.fm.solves} FE solves)")
    final = cal.residuals(theta, cal.calibration_scans, gradient=True)
    r = np.concatenate([v.r for v in final.values()])
    if options.objective == "nipple":
        unc, check, ci95, profile = _nipple_uncertainty(cal, theta, r, say)
    else:
        dr = np.concatenate([v.dr for v in final.values()])
        pts = np.concatenate([v.points_mm for v in final.values()])
        area = _area(cal) if options.objective == "surface" else None
        unc = gauss_newton_uncertainty(c1, r, dr, pts, area_mm2=area)
        check, ci95 = _mesh_check(cal, theta, unc, say)
        if options.profile_points >= 2:
            say(f"likelihood profile over c1: {options.profile_points} points")
        profile = _profile(cal, theta, unc.se_ln_c1, unc.n_effective)
    _write_reference_mesh(work / "calibration" / "reference_mesh.vtu", cal)
    targets = cal.targets()
    say(f"final state of {len(targets)} scans, error maps")
    scans = {s.name: _final_scan(cal, s, theta, work) for s in targets}
    doc = {
        "c1_pa": c1,
        "c1_ci95_pa": list(ci95) if ci95 is not None else None,
        "objective": options.objective,
        "objective_value_mm2": float(res.fun),
        "reference_state": options.reference_state,
        "uncertainty": asdict(unc) | {"mesh_check": asdict(check) if check else None},
        "frames": {
            "fiducial": "scans mapped by the fiducial registration only (no ICP)",
            "icp": "after rigid ICP of the measured onto the simulated surface "
            "(biased low: it absorbs part of the model error)",
        },  # fmt: skip
        "scans": scans,
        "iterations": int(res.nit),
        "fe_solves": int(cal.fm.solves),
        "reference_recovery": {
            "method": cal.fm.unload_method
            if options.reference_state == "unload"
            else "none (shortcut)",
            "inverted_elements": cal.fm.inverted_reference_elements,
        },  # fmt: skip
        "history": cal.history,
        "profile": profile,
        "mesh": {
            "n_tets": cal.mesh.n_tets,
            "n_nodes": cal.mesh.n_nodes,
            "size_mm": options.mesh_size_mm,
            "failed_sizes": attempts,
            "formulation": options.formulation,
        },  # fmt: skip
        "wall_s": time.perf_counter() - t0,
        "provenance": provenance(
            inputs={"session": session.folder / "session.toml"}
            | {
                f"{s.name}/ingest.json": work / "scans" / s.name / "ingest.json"
                for s in session.scans
            },
            parameters=asdict(options),
        ),
    }
    write_json_atomic(work / "calibration.json", doc)
    return doc


def _area(cal: Calibrator) -> float:
    total = 0.0
    for s in cal.calibration_scans:
        v, f = s.vertices_mm, s.faces
        off = ~s.back_plate[f].all(axis=1)
        tri = v[f[off]]
        total += (
            0.5
            * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        )
    return float(total)
