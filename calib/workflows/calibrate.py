"""``phantom-calib calibrate``: ingest (when needed), fit, evaluate, write WORK.

Writes ``WORK/calibration.json`` and ``WORK/calibration/`` as one run
(:class:`calib.io.RunOutputs`): the stress-free reference mesh, and per scan the
deformed mesh (with the derivative of every vertex position in ln c1, so the
validation can propagate the c1 interval without FE), the error map (PNG, two views)
and the measured surface with a per-vertex error (PLY).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from ..data.ingest import stale_reasons
from ..data.measurements import load_measurements
from ..data.session import SessionError, load_session, session_inputs
from ..evaluation import ScanEvaluation, check_postures, evaluate, model_fit_with_postures
from ..fitting import Calibration, CalibrationOptions, fit
from ..fitting.result import phantom_frame
from ..io import (
    WORK_OPTION,
    RunOutputs,
    StaleOutputError,
    check_out_apart,
    check_out_folder,
    check_replaceable,
    input_records,
    locking_work,
    provenance,
    run_id_of,
)
from ..report.maps import (
    save_figure,
    shared_error_scale_mm,
    surface_error_figure,
    write_error_ply,
)

__all__ = ["run_calibration", "write_calibration"]

log = logging.getLogger(__name__)

FOLDER, RECORD = "calibration", "calibration.json"


def _scan_files(
    run: RunOutputs, cal: Calibration, ev: ScanEvaluation, R: np.ndarray, *, vmax_mm: float
) -> list[str]:
    from fem.io import write_mesh

    c = cal.calibrator
    scan = c.measurements.scans[ev.name]
    m = ev.metrics
    write_error_ply(
        run.path(f"{ev.name}_error.ply"), scan.vertices_mm, scan.faces, m.vertex_error_mm
    )
    err = m.vertex_error_mm[scan.scored]
    # the phantom frame and the signed scale of validate's and diagnose's maps (review
    # AX: this one was a see-through scatter in the reference frame, and unsigned)
    fig = surface_error_figure(
        scan,
        m.vertex_error_mm,
        R,
        f"{ev.name}: surface error at c1 = {cal.c1_pa:.0f} Pa, mean |e| {np.mean(np.abs(err)):.2f}"
        " mm (fiducial registration; colour scale shared by the scans)",
        vmax=vmax_mm,
    )
    save_figure(fig, run.path(f"{ev.name}_error.png"))
    X = c.fm.stress_free_nodes_mm
    data = {
        "displacement_mm": ev.positions_mm - X,
        "displacement_from_reference_mm": ev.positions_mm - c.mesh.nodes_mm,
    }
    if ev.dpositions_mm is not None:
        data["dposition_dlnc1_mm"] = ev.dpositions_mm
    write_mesh(
        c.mesh.with_nodes(ev.positions_mm), run.path(f"{ev.name}_deformed.vtu"), point_data=data
    )
    return [
        f"{FOLDER}/{ev.name}_error.ply",
        f"{FOLDER}/{ev.name}_error.png",
        f"{FOLDER}/{ev.name}_deformed.vtu",
    ]


def _scan_json(ev: ScanEvaluation, files: list[str]) -> dict:
    out = ev.to_json()
    if ev.failed is None:
        out["model"] = {
            "nipple_mm": None,
            "tumour_mm": None if ev.tumour_mm is None else ev.tumour_mm.tolist(),
            "dtumour_dlnc1_mm": None if ev.dtumour_mm is None else ev.dtumour_mm.tolist(),
        }
        out["files"] = files
    return out


def _write_prestress(run, c) -> dict:
    """The prestressed reference's files (loaded mesh, inverse state) and its model block.

    The prestress is rebuilt from them by :func:`fem.prestress.compute_prestress` with the
    saved inverse state as its start (no Newton step at the calibrated c1).
    """
    from fem.io import write_mesh

    ps = c.fm.prestress
    write_mesh(c.mesh, run.path("loaded_reference_mesh.vtu"))
    np.savez(
        run.path("reference_prestress.npz"),
        inverse_state=ps.inverse_state,
        gravity_m_s2=np.asarray(ps.gravity_m_s2, float),
    )
    tumour = None if c.tumour is None else c.tumour.place_mm(c.mesh.nodes_mm).tolist()
    return {
        "method": "inverse (spatial; curved stress-free elements)",
        "mesh": f"{FOLDER}/loaded_reference_mesh.vtu",
        "state": f"{FOLDER}/reference_prestress.npz",
        "formulation": ps.formulation,
        "tumour_reference_mm": tumour,
    }


def write_calibration(
    work: str | Path,
    calibration: Calibration,
    evaluations: dict[str, ScanEvaluation],
    *,
    inputs: dict,
    wall_s: float,
    ingest_run_id: str | None = None,
    scans_source: dict | None = None,
) -> dict:
    """Write ``WORK/calibration.json`` and ``WORK/calibration/`` as one run; return the record.

    ``inputs`` maps names to input paths or to :func:`calib.io.input_records` entries
    taken when they were read. ``ingest_run_id`` is the ``WORK/scans`` run the
    measurements were read from (default:
    the one there now); a WORK whose scans were ingested again since is refused
    (:class:`calib.io.StaleOutputError`: review AN, the record named scans it never
    fitted). ``scans_source`` is the session's ``[source]`` (recorded as
    ``scans_source``; null where it says nothing).

    Raises
    ------
    calib.io.StaleOutputError
        ``WORK/scans`` holds another ingest run than ``ingest_run_id``; nothing written.
    """
    from fem.io import write_mesh

    held = run_id_of(Path(work) / "scans")
    if ingest_run_id is not None and held != ingest_run_id:
        raise StaleOutputError(
            f"{Path(work) / 'scans'} was ingested again during this calibration (it read "
            f"ingest run {ingest_run_id}, the folder now holds {held}); nothing written: "
            "calibrate again"
        )

    c = calibration.calibrator
    nipple = int(c.mesh.node_set("nipple")[0])
    with RunOutputs(work, folder=FOLDER, record=RECORD) as run:
        write_mesh(c.mesh.with_nodes(c.fm.stress_free_nodes_mm), run.path("reference_mesh.vtu"))
        measured = c.measurements.scans
        vmax_mm = shared_error_scale_mm(
            ev.metrics.vertex_error_mm[measured[ev.name].scored]
            for ev in evaluations.values()
            if ev.failed is None
        )
        R = phantom_frame(c.measurements.reference, measured.values())
        scans = {}
        for name, ev in evaluations.items():
            solved = ev.failed is None
            files = _scan_files(run, calibration, ev, R, vmax_mm=vmax_mm) if solved else []
            scans[name] = _scan_json(ev, files)
            if solved:
                scans[name]["model"]["nipple_mm"] = ev.positions_mm[nipple].tolist()
        doc = calibration.to_json(
            scans=scans,
            provenance=provenance(inputs=inputs, parameters=asdict(calibration.options)),
        )
        doc["model"]["reference_mesh"] = f"{FOLDER}/reference_mesh.vtu"
        doc["ingest_run_id"] = held
        doc["scans_source"] = dict(scans_source) if scans_source else None
        prestress = None
        if c.fm.prestressed:
            c.fm.stress_free(calibration.theta)  # the prestress at the calibrated c1 (cached)
            prestress = _write_prestress(run, c)
        doc["model"]["prestress"] = prestress
        # with the final states of every scan, and a straight fit the curved one replaced
        doc["fe_solves"] = calibration.optimiser.set_aside_fe_solves + int(c.fm.solves)
        doc["wall_s"] = wall_s
        record = run.commit(doc)
    _drop_outputs_of_another_fit(Path(work), record["run_id"])
    return record


def _drop_outputs_of_another_fit(work: Path, run_id: str) -> None:
    """Remove ``validate``'s outputs of the calibration just replaced.

    Review AN: a calibrate stopped (or failed) in its closing validate left the old fit's
    ``validation.json`` and ``validation/report.html`` beside the new calibration. A
    diagnosis (35 minutes of work, review AP) stays: it names the calibration it was made
    from (``calibration_run_id``), which the view checks.
    """
    import shutil

    record = work / "validation.json"
    try:
        made_from = json.loads(record.read_text()).get("calibration_run_id")
    except FileNotFoundError:
        return
    except (OSError, ValueError, AttributeError) as exc:  # unreadable: not this fit's
        log.warning("%s: unreadable (%s)", record, exc)
        made_from = None
    if made_from != run_id:
        record.unlink(missing_ok=True)
        shutil.rmtree(work / "validation", ignore_errors=True)
        log.warning(
            "removed %s and %s/: they were made from the calibration this one replaced",
            *(record, work / "validation"),
        )


def _with_posture_check(calibration: Calibration, evaluations, say) -> Calibration:
    """The calibration with the posture-consistency test in its ``model_fit``."""
    checked = check_postures(calibration, evaluations)
    if checked is None:
        return calibration
    test, names = checked
    say(_posture_line(test, names))
    # what a misfit means for the interval is the summary's WARNING, printed next (review
    # AX: a progress line said it too, the misfit four times in one run)
    merged = model_fit_with_postures(calibration.model_fit, test, names)
    return replace(calibration, model_fit=merged)


def _posture_line(test, names: dict) -> str:
    """The posture-consistency test in one progress line."""
    own = ", ".join(f"{names[e.label]} {np.exp(e.theta):.0f} Pa" for e in test.estimates)
    if test.verdict == "consistent":
        return (
            f"posture consistency: every scan alone asks for the same c1 ({own}; Cochran Q "
            f"p = {test.p_value:.2g} >= {test.alpha:g})"
        )
    return (
        f"POSTURE INCONSISTENCY: the scans alone ask for different c1 ({own}; Cochran Q "
        f"p = {test.p_value:.2g} < {test.alpha:g}): the model misses an effect that "
        "changes with posture, or its mesh errs unlike in each posture (the test leaves the "
        "model mesh's discretisation out: a homogeneous quick twin on a 14 mm mesh fires "
        "it); `phantom-calib diagnose` tells which"
    )


@locking_work("calibrate", create=True)
def run_calibration(scans_dir, work, options: CalibrationOptions, *, progress=None) -> dict:
    """Calibrate c1 on a scan session and write ``WORK/calibration.json`` and maps.

    Parameters
    ----------
    scans_dir : path
        Folder with ``session.toml``.
    work : path
        Work folder; the scans are ingested into it first when their results are missing.
    options : CalibrationOptions
    progress : callable, optional
        Called with a line of text at every step.

    Returns
    -------
    dict
        The ``calibration.json`` record.
    """
    say = progress or log.info
    t0 = time.perf_counter()
    work = Path(work)
    check_out_folder(work, option=WORK_OPTION)
    session = load_session(scans_dir)
    # review BI, BK: hashed as read, not when the record is written
    session_read = input_records({"session": session.folder / "session.toml"})
    check_out_apart(work, session_inputs(session), what="the scan data", option=WORK_OPTION)
    check_replaceable(work, ("scans", FOLDER), command="calibrate")  # it may ingest first
    if not session.by_role("calibration"):
        raise SessionError(
            f"{session.folder / 'session.toml'}: no scan has role 'calibration' (calibrate "
            f"fits c1 to them; scans: {[(s.name, s.role) for s in session.scans]})"
        )
    reasons = stale_reasons(work, session)
    if reasons:
        from .ingest import run_ingest

        say(f"ingesting the scans ({'; '.join(reasons)})")
        ingested = run_ingest(scans_dir, work)
        say(ingested.summary_table)  # as `phantom-calib ingest` prints it (review AX)
    meas = load_measurements(work, session)
    fitted_run = run_id_of(work / "scans")
    inputs = session_read | input_records(
        {f"{s.name}/ingest.json": work / "scans" / s.name / "ingest.json" for s in session.scans}
    )
    calibration = fit(meas, options, density_kg_m3=session.density_kg_m3, progress=say)
    targets = [n for n, s in meas.scans.items() if s.role != "reference"]
    say(f"final state of {len(targets)} scans, error maps")
    evaluations = evaluate(calibration, meas, scans=targets)
    calibration = _with_posture_check(calibration, evaluations, say)
    return write_calibration(
        work,
        calibration,
        evaluations,
        inputs=inputs,
        wall_s=time.perf_counter() - t0,
        ingest_run_id=fitted_run,
        scans_source=session.source,
    )
