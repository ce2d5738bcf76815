"""``phantom-calib ingest``: every scan of a session to surfaces, landmarks and frames.

Writes per scan ``WORK/scans/<name>/surface.ply`` (scan LPS mm), ``surface_ref.ply``
(reference LPS mm), ``mask.nii.gz`` and ``ingest.json`` (see the README).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .io import provenance, write_json_atomic
from .session import Session, load_session

__all__ = ["IngestResult", "ingest_session", "load_ingest"]

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


def _map(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return (T[:3, :3] @ np.asarray(p, float).T).T + T[:3, 3]


def _match_constellation(ref_pts: np.ndarray, pts: np.ndarray, iterations: int = 15):
    """Affine map taking ``pts`` onto ``ref_pts`` from iterated mutual nearest neighbours.

    Gravity moves the inclusions by 10-20 mm between postures but keeps their
    constellation: an affine fit of mutual matches absorbs most of the motion.
    """
    A = np.eye(4)
    for _ in range(iterations):
        moved = _map(A, pts)
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
    idx = {ref: imaging.select_tumour(ref_pts, r.inclusions.diameters_mm,
                                      hint_lps_mm=session.tumour_hint_lps_mm)}  # fmt: skip
    for name, res in scans.items():
        if name == ref:
            continue
        pts = _map(fiducial_regs[name].T_ref_from_scan, res.inclusions.centres_lps_mm)
        if len(pts) == 0:
            continue
        A = _match_constellation(ref_pts, pts) if len(pts) >= 4 else np.eye(4)
        # only inclusions of the tracked one's size (diameters are measured to ~0.2 mm)
        d_ref = r.inclusions.diameters_mm[idx[ref]]
        d = res.inclusions.diameters_mm
        same = np.flatnonzero(np.abs(d - d_ref) <= max(1.0, 0.15 * d_ref))
        cand = same if len(same) else np.arange(len(d))
        k = imaging.select_tumour(_map(A, pts[cand]), d[cand], hint_lps_mm=ref_pts[idx[ref]])
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
        marks = {n: {"nipple": r.nipple_lps_mm} | ({"tumour": r.tumour_lps_mm}
                 if r.tumour_lps_mm is not None else {}) for n, r in scans.items()}  # fmt: skip
    return registration.register_scans(
        fids,
        reference=session.reference.name,
        gravity_scanner=session.gravity_scanner,
        nominal_angles_deg=angles if len(angles) >= 2 else None,
        landmarks_by_scan=marks,
    )


def _write_scan(work: Path, name: str, res, reg, session: Session) -> None:
    import imaging

    folder = work / "scans" / name
    folder.mkdir(parents=True, exist_ok=True)
    imaging.write_ply(folder / "surface.ply", res.surface)
    ref_vertices = _map(reg.T_ref_from_scan, res.surface.vertices_lps_mm)
    ref_surface = replace(res.surface, vertices_lps_mm=ref_vertices)
    imaging.write_ply(folder / "surface_ref.ply", ref_surface)
    imaging.write_nifti(res.mask, folder / "mask.nii.gz")
    entry = next(s for s in session.scans if s.name == name)
    doc = {"name": name, "role": entry.role, "source": str(entry.path)}
    doc |= res.to_json_dict() | reg.to_json()
    doc["frames"] = {
        "scan": "this scan's LPS frame (mm): fiducials_lps_mm, nipple_lps_mm, tumour_lps_mm, "
        "inclusions, surface.ply",
        "reference": "the reference scan's LPS frame (mm): surface_ref.ply, gravity_ref; "
        "T_ref_from_scan maps scan points to it",
    }
    write_json_atomic(folder / "ingest.json", doc)


def ingest_session(scans_dir: str | Path, work: str | Path, *, progress=None) -> IngestResult:
    """Process every scan of a session and register them to the reference scan.

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
    import registration

    session = load_session(scans_dir)
    work = Path(work)
    tick = progress or (lambda name: log.info("processed scan %s", name))
    scans = {s.name: _process(s, session, tick) for s in session.scans}
    regs = _register(session, scans, landmarks=False)
    tumour = _track_tumour(session, scans, regs)
    scans = {n: _with_tumour(r, tumour[n]) for n, r in scans.items()}
    regs = _register(session, scans, landmarks=True)
    for name, res in scans.items():
        _write_scan(work, name, res, regs[name], session)
    table = registration.format_registration_table(regs)
    write_json_atomic(
        work / "ingest_summary.json",
        {"scans": {n: r.to_json() for n, r in regs.items()},
         "provenance": provenance(inputs={"session": session.folder / "session.toml"})},
    )  # fmt: skip
    return IngestResult(session, scans, regs, tumour, table)


def load_ingest(work: str | Path, name: str) -> dict:
    """Read ``work/scans/<name>/ingest.json``."""
    import json

    path = Path(work) / "scans" / name / "ingest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: run `phantom-calib ingest` first")
    return json.loads(path.read_text())
