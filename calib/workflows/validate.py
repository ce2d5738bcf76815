"""``phantom-calib validate``: the validation report of a calibrated WORK, from saved states.

Writes ``WORK/validation.json`` and ``WORK/validation/`` (``report.md``,
``report.html`` and the figures) as one run; no FE solve (the deformed states and
their derivatives in ln c1 are those ``calibrate`` saved).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..data.work import WorkFolder, read_work
from ..io import (
    RunOutputs,
    atomic_write,
    check_replaceable,
    check_work_writable,
    input_records,
    locking_work,
    provenance,
)
from ..report.maps import save_figure
from ..report.validation import (
    error_by_displacement_figure,
    error_surface_figure,
    outline_figure,
    validation_error_scale_mm,
    validation_html,
    validation_markdown,
)
from ..validation import Validation, validate_work

__all__ = ["run_validation"]

log = logging.getLogger(__name__)
FOLDER, RECORD = "validation", "validation.json"


def _outline(run: RunOutputs, work: WorkFolder, v: Validation, name: str) -> str | None:
    import imaging
    from registration import apply_transform

    from ..model.residuals import SimulatedSurface

    mask_path = work.path / "scans" / name / "mask.nii.gz"
    if not mask_path.is_file():
        return None
    scan = work.measurements.scans[name]
    T_scan_from_ref = np.linalg.inv(scan.T_ref_from_scan)
    model = apply_transform(T_scan_from_ref, work.states[name].positions_mm)
    centre_ref = scan.tumour_mm if scan.tumour_mm is not None else scan.nipple_mm
    centre = apply_transform(T_scan_from_ref, centre_ref)
    faces = SimulatedSurface.of(work.mesh).faces
    said = "the tumour" if scan.tumour_mm is not None else "the nipple"
    simulated = work.states[name].tumour_mm
    if simulated is not None and scan.tumour_mm is not None:
        simulated = apply_transform(T_scan_from_ref, np.asarray(simulated, float))
    else:
        simulated = None
    fig = outline_figure(
        v.scans[name],
        imaging.read_volume(mask_path),
        model,
        faces,
        centre,
        centre=said,
        model_tumour_lps_mm=simulated,
    )
    save_figure(fig, run.path(f"{name}_outlines.png"))
    return f"{name}_outlines.png"


def _figures(run: RunOutputs, work: WorkFolder, v: Validation) -> dict[str, list[str]]:
    R = np.asarray(work.record["model"]["R_ref_from_phantom"], float)
    vmax = validation_error_scale_mm(v, work.measurements.scans)
    figures: dict[str, list[str]] = {}
    for sv in v.scans.values():
        files = []
        fig = error_surface_figure(sv, work.measurements.scans[sv.name], R, vmax=vmax)
        save_figure(fig, run.path(f"{sv.name}_error_surface.png"))
        files.append(f"{sv.name}_error_surface.png")
        if sv.role == "validation":
            outline = _outline(run, work, v, sv.name)
            if outline:
                files.append(outline)
        figures[sv.name] = files
    save_figure(
        error_by_displacement_figure(list(v.scans.values())), run.path("error_by_displacement.png")
    )
    figures["error by displacement"] = ["error_by_displacement.png"]
    return figures


@locking_work("validate")
def run_validation(work: str | Path, *, progress=None, on_validation=None) -> dict:
    """Validate a calibrated work folder and write the report.

    Parameters
    ----------
    work : path
        A folder ``phantom-calib calibrate`` wrote.
    progress : callable, optional
        Called with a line of text at every step.
    on_validation : callable, optional
        Called with the :class:`~calib.validation.Validation` computed and the written
        record, once it is written (``calib.validate`` hands it to a loaded ``Work``).

    Returns
    -------
    dict
        The ``validation.json`` record.
    """
    say = progress or log.info
    t0 = time.perf_counter()
    wf = read_work(work)
    read = input_records({"calibration": wf.path / "calibration.json"})  # review BK: as read
    check_work_writable(wf.path, f"{FOLDER}/ and {RECORD}")
    check_replaceable(wf.path, (FOLDER,), option="WORK")  # before the work, not at its end
    say(f"validating {len(wf.states)} scans at c1 = {wf.c1_pa:.1f} Pa (saved states, no FE)")
    v = validate_work(wf)
    with RunOutputs(wf.path, folder=FOLDER, record=RECORD) as run:
        say("figures: error surfaces, error by displacement, outlines")
        figures = _figures(run, wf, v)
        md = validation_markdown(v, figures)
        page = validation_html(v, figures)
        atomic_write(run.path("report.md"), lambda p: p.write_text(md))
        atomic_write(run.path("report.html"), lambda p: p.write_text(page))
        doc = v.to_json() | {
            "files": [f"{FOLDER}/report.md", f"{FOLDER}/report.html"]
            + [f"{FOLDER}/{f}" for fs in figures.values() for f in fs],
            "calibration_run_id": wf.record.get("run_id"),
            "wall_s": time.perf_counter() - t0,
            "provenance": provenance(inputs=read),
        }
        written = run.commit(doc)
    if on_validation is not None:
        on_validation(v, written)
    return written
