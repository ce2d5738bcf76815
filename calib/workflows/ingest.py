"""``phantom-calib ingest``: write every scan's surfaces, landmarks and frames into WORK.

Per scan ``WORK/scans/<name>/surface.ply`` (scan LPS mm), ``surface_ref.ply`` (reference
LPS mm), ``mask.nii.gz`` and ``ingest.json``, and ``WORK/ingest_summary.json`` (see the
README's output contract).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ..data.ingest import IngestResult, ingest_inputs, ingest_scans
from ..data.session import Session, load_session, session_inputs
from ..io import (
    WORK_OPTION,
    RunOutputs,
    check_out_apart,
    check_out_folder,
    check_replaceable,
    input_records,
    locking_work,
    provenance,
    write_json_atomic,
)

__all__ = ["run_ingest", "write_ingest"]


def _write_scan(
    root: Path,
    name: str,
    res,
    reg,
    session: Session,
    source_sha256: str,
    *,
    tracking=None,
    choice=None,
) -> None:
    import imaging
    from registration import apply_transform

    folder = root / name
    folder.mkdir(parents=True, exist_ok=True)
    imaging.write_ply(folder / "surface.ply", res.surface)
    ref_vertices = apply_transform(reg.T_ref_from_scan, res.surface.vertices_lps_mm)
    imaging.write_ply(
        folder / "surface_ref.ply", replace(res.surface, vertices_lps_mm=ref_vertices)
    )
    imaging.write_nifti(res.mask, folder / "mask.nii.gz")
    entry = next(s for s in session.scans if s.name == name)
    doc = {
        "name": name,
        "role": entry.role,
        "source": str(entry.path),
        "source_sha256": source_sha256,
    }
    doc |= res.to_json_dict() | reg.to_json()
    if tracking is not None:  # per inclusion its identity in the reference scan
        _add_tracking(doc, tracking, choice)
    doc["frames"] = {
        "scan": "this scan's LPS frame (mm): fiducials_lps_mm, nipple_lps_mm, tumour_lps_mm, "
        "inclusions, surface.ply",
        "reference": "the reference scan's LPS frame (mm): surface_ref.ply, gravity_ref; "
        "T_ref_from_scan maps scan points to it",
    }
    write_json_atomic(folder / "ingest.json", doc)


def _add_tracking(doc: dict, tracking, choice) -> None:
    """Per-inclusion ``reference_index`` / ``match_confidence`` and the ``tracking`` block."""
    from registration import CONFIDENCE_DEFINITION

    for inc, i, c in zip(
        doc["inclusions"], tracking.reference_index, tracking.confidence, strict=True
    ):
        inc["reference_index"] = i
        inc["match_confidence"] = c
    doc["tracking"] = tracking.to_json() | {
        "tumour_reference_index": None if choice is None else choice.reference_index,
        "selection": None if choice is None else choice.reason,
        "method": "constellation match to the reference scan's inclusions (sizes, relative "
        "positions, nipple anchor, smooth deformation): registration.match_constellation",
        "match_confidence_definition": CONFIDENCE_DEFINITION,
    }


def write_ingest(
    work: str | Path, result: IngestResult, *, inputs: dict | None = None, session_record=None
) -> dict:
    """Write an :class:`~calib.data.ingest.IngestResult` into ``work`` as one run.

    ``WORK/scans/`` is staged and swapped in whole, and ``WORK/ingest_summary.json`` (with
    the fingerprints of the session and of every scan source, which ``calibrate`` checks)
    is written last (:class:`calib.io.RunOutputs`): a failed or killed ingest leaves the
    previous results as they were, never a mix.

    Parameters
    ----------
    work : str or Path
        The work folder.
    result : IngestResult
        What :func:`calib.data.ingest.ingest_scans` made.
    inputs : dict, optional
        :func:`calib.data.ingest.ingest_inputs` of the session, taken before its scans
        were read (default: now).
    session_record : dict, optional
        :func:`calib.io.input_records` of ``session.toml``, taken when it was read
        (default: now).

    Returns
    -------
    dict
        The ``ingest_summary.json`` record.
    """
    if inputs is None:
        inputs = ingest_inputs(result.session)
    if session_record is None:
        session_record = input_records({"session": result.session.folder / "session.toml"})
    with RunOutputs(work, folder="scans", record="ingest_summary.json") as run:
        for name, res in result.scans.items():
            _write_scan(
                run.stage,
                name,
                res,
                result.registrations[name],
                result.session,
                inputs["sources_sha256"][name],
                tracking=result.tracking.get(name),
                choice=result.tumour_choice,
            )
        return run.commit(
            {
                "scans": {n: r.to_json() for n, r in result.registrations.items()},
                "inputs": inputs,
                "provenance": provenance(inputs=session_record),
            }
        )


@locking_work("ingest", create=True)
def run_ingest(scans_dir: str | Path, work: str | Path, *, progress=None) -> IngestResult:
    """Ingest the session in ``scans_dir`` and write the results into ``work``.

    Parameters
    ----------
    scans_dir : path
        Folder with ``session.toml``.
    work : path
        Output folder (created); per-scan results go to ``work/scans/<name>/``.
    progress : callable, optional
        Called with each scan's name when it has been processed.

    Returns
    -------
    IngestResult
    """
    check_out_folder(work, option=WORK_OPTION)  # before the work, not after it
    session = load_session(scans_dir)
    check_out_apart(work, session_inputs(session), what="the scan data", option=WORK_OPTION)
    check_replaceable(work, ("scans",))
    # review BI: fingerprinted before they are read, so that a source changed during the
    # run leaves results that later commands call stale (after, they were called current)
    inputs = ingest_inputs(session)
    session_record = input_records({"session": session.folder / "session.toml"})
    result = ingest_scans(session, progress=progress)
    write_ingest(work, result, inputs=inputs, session_record=session_record)
    return result
