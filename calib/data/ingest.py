"""Every scan of a session to surfaces, landmarks and frames (no files written).

:func:`ingest_scans` segments, surfaces and registers the scans;
:mod:`calib.workflows.ingest` writes the results into ``WORK/scans/<name>/``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from registration import apply_transform

from .session import Session

__all__ = [
    "IngestResult",
    "StaleIngestError",
    "ingest_inputs",
    "ingest_scans",
    "load_ingest",
    "stale_reasons",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IngestResult:
    """The processed session: per-scan imaging results and registrations."""

    session: Session
    scans: dict  # name -> imaging.ScanResult (scan LPS frame)
    registrations: dict  # name -> registration.ScanRegistration
    tumour_index: dict  # name -> index of the tracked inclusion
    summary_table: str


def _process(entry, session: Session, progress):
    import imaging

    volume = imaging.read_volume(entry.path)
    result = imaging.process_scan(volume, expected_fiducials=session.expected_fiducials)
    progress(entry.name)
    return result


def _match_constellation(ref_pts: np.ndarray, pts: np.ndarray, iterations: int = 15):
    """Affine map taking ``pts`` onto ``ref_pts`` from iterated mutual nearest neighbours.

    Gravity moves the inclusions by 10-20 mm between postures but keeps their
    constellation: an affine fit of mutual matches absorbs most of the motion.
    """
    A = np.eye(4)
    for _ in range(iterations):
        moved = apply_transform(A, pts)
        d = np.linalg.norm(moved[:, None] - ref_pts[None], axis=2)
        fwd, back = d.argmin(axis=1), d.argmin(axis=0)
        mutual = np.flatnonzero(back[fwd] == np.arange(len(pts)))
        if len(mutual) < 4:
            break
        src = np.column_stack([pts[mutual], np.ones(len(mutual))])
        sol, *_ = np.linalg.lstsq(src, ref_pts[fwd[mutual]], rcond=None)
        A = np.eye(4)
        A[:3, :] = sol.T
    return A


def _track_tumour(session: Session, scans: dict, fiducial_regs: dict) -> dict:
    """Choose the tracked inclusion in every scan consistently with the reference.

    The reference scan's tumour is the inclusion nearest to the session's hint (else the
    largest); in every other scan it is the inclusion of similar diameter that the
    constellation match (:func:`_match_constellation`, in the reference frame) puts nearest.
    """
    import imaging

    ref = session.reference.name
    r = scans[ref]
    ref_pts = r.inclusions.centres_lps_mm
    idx = {
        ref: imaging.select_tumour(
            ref_pts, r.inclusions.diameters_mm, hint_lps_mm=session.tumour_hint_lps_mm
        )
    }
    for name, res in scans.items():
        if name == ref:
            continue
        pts = apply_transform(fiducial_regs[name].T_ref_from_scan, res.inclusions.centres_lps_mm)
        if len(pts) == 0:
            continue
        A = _match_constellation(ref_pts, pts) if len(pts) >= 4 else np.eye(4)
        # only inclusions of the tracked one's size (diameters are measured to ~0.2 mm)
        d_ref = r.inclusions.diameters_mm[idx[ref]]
        d = res.inclusions.diameters_mm
        same = np.flatnonzero(np.abs(d - d_ref) <= max(1.0, 0.15 * d_ref))
        cand = same if len(same) else np.arange(len(d))
        k = imaging.select_tumour(
            apply_transform(A, pts[cand]), d[cand], hint_lps_mm=ref_pts[idx[ref]]
        )
        idx[name] = int(cand[k])
    return idx


def _with_tumour(res, i: int):
    if len(res.inclusions.centres_lps_mm) == 0:
        return res
    return replace(res, tumour_lps_mm=res.inclusions.centres_lps_mm[i])


def _register(session: Session, scans: dict, landmarks: bool):
    import registration

    fids = {n: r.fiducials_lps_mm for n, r in scans.items()}
    angles = {s.name: s.posture_angle_deg for s in session.scans if s.posture_angle_deg is not None}
    marks = None
    if landmarks:
        marks = {
            n: {"nipple": r.nipple_lps_mm}
            | ({"tumour": r.tumour_lps_mm} if r.tumour_lps_mm is not None else {})
            for n, r in scans.items()
        }
    return registration.register_scans(
        fids,
        reference=session.reference.name,
        gravity_scanner=session.gravity_scanner,
        nominal_angles_deg=angles if len(angles) >= 2 else None,
        landmarks_by_scan=marks,
    )


def ingest_scans(session: Session, *, progress=None) -> IngestResult:
    """Process every scan of a session and register them to the reference scan.

    Pure: reads the scan volumes and returns the results; writing them into a work
    folder is :func:`calib.workflows.ingest.run_ingest`'s job.

    Parameters
    ----------
    session : Session
    progress : callable, optional
        Called with each scan's name when it has been processed.

    Returns
    -------
    IngestResult
    """
    import registration

    tick = progress or (lambda name: log.info("processed scan %s", name))
    scans = {s.name: _process(s, session, tick) for s in session.scans}
    regs = _register(session, scans, landmarks=False)
    tumour = _track_tumour(session, scans, regs)
    scans = {n: _with_tumour(r, tumour[n]) for n, r in scans.items()}
    regs = _register(session, scans, landmarks=True)
    table = registration.format_registration_table(regs)
    return IngestResult(session, scans, regs, tumour, table)


def load_ingest(work: str | Path, name: str) -> dict:
    """Read ``work/scans/<name>/ingest.json``."""
    import json

    path = Path(work) / "scans" / name / "ingest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: run `phantom-calib ingest` first")
    return json.loads(path.read_text())


class StaleIngestError(RuntimeError):
    """The ingest results in a work folder are not those of the current scans."""


def ingest_inputs(session: Session) -> dict:
    """Fingerprints of what ingest reads.

    The session (:meth:`Session.ingest_fingerprint`) and every scan's source
    (:func:`calib.io.source_sha256`).
    """
    from ..io import source_sha256

    return {
        "session_sha256": session.ingest_fingerprint(),
        "sources_sha256": {s.name: source_sha256(s.path) for s in session.scans},
    }


def stale_reasons(work: str | Path, session: Session) -> list[str]:
    """Why the ingest results in ``work`` do not belong to ``session`` (empty: they do).

    Compares the fingerprints recorded in ``WORK/ingest_summary.json`` with the session
    and the scan sources as they are now.
    """
    from ..io import StaleOutputError, check_run

    work = Path(work)
    try:
        doc = check_run(work, folder="scans", record="ingest_summary.json")
    except FileNotFoundError:
        return ["no ingest results"]
    except StaleOutputError:
        return ["the ingest results are from an interrupted run"]
    recorded = doc.get("inputs")
    if recorded is None:
        return ["the ingest results carry no fingerprints (an older phantom-calib)"]
    now = ingest_inputs(session)
    reasons = []
    if recorded["session_sha256"] != now["session_sha256"]:
        reasons.append(
            "session.toml changed (its reference scan, postures, landmarks, "
            "scanner gravity, marker count or list of scans)"
        )
    old = recorded.get("sources_sha256", {})
    changed = [n for n, h in now["sources_sha256"].items() if old.get(n) != h]
    if changed:
        reasons.append(f"scan data changed or added: {changed}")
    missing = [
        s.name for s in session.scans if not (work / "scans" / s.name / "ingest.json").is_file()
    ]
    if missing:
        reasons.append(f"no ingest results for {missing}")
    return reasons
