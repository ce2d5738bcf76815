"""Every scan of a session to surfaces, landmarks and frames (no files written).

:func:`ingest_scans` segments, surfaces and registers the scans and tracks every
inclusion across them (:func:`registration.match_constellation`);
:mod:`calib.workflows.ingest` writes the results into ``WORK/scans/<name>/``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from registration import apply_transform

from .session import Session

__all__ = [
    "TUMOUR_MIN_CONFIDENCE",
    "InclusionTracking",
    "IngestResult",
    "StaleIngestError",
    "TumourChoice",
    "TumourNotFoundWarning",
    "TumourHintWarning",
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
    tumour_index: dict  # name -> index of the tracked inclusion (None: not found there)
    summary_table: str
    tracking: dict = field(default_factory=dict)  # name -> InclusionTracking
    tumour_choice: TumourChoice | None = None  # the reference's tracked inclusion and why

    def __repr__(self) -> str:  # review AI: the generated one ran to 30,000 characters
        return f"IngestResult({str(self.session.folder)!r}, {len(self.scans)} scans)"

    def _repr_html_(self) -> str:
        import html

        return f"<pre>{html.escape(repr(self))}\n\n{html.escape(self.summary_table)}</pre>"


def _process(entry, session: Session, progress):
    import imaging

    volume = imaging.read_volume(entry.path)
    try:
        result = imaging.process_scan(volume, expected_fiducials=session.expected_fiducials)
    except imaging.FiducialError as exc:
        # review AX: the count it expected comes from session.toml, which it did not say
        toml = session.folder / "session.toml"
        raise type(exc)(
            f"{exc} (the count expected is {toml}'s [phantom] fiducials = "
            f"{session.expected_fiducials}: where the phantom has another number of "
            "markers, set it there)"
        ) from exc
    progress(entry.name)
    return result


class TumourNotFoundWarning(UserWarning):
    """The tracked tumour has no matching inclusion in a scan (its tumour is left unset)."""


class TumourHintWarning(UserWarning):
    """No inclusion of the reference scan lies near the ``[landmarks] tumour`` hint."""


#: The inclusion nearest the tumour hint is taken for the tumour; farther than its own
#: radius plus this (mm) from the hint, the tumour itself was likely not segmented (too
#: large, too small, darker than the body) and the pick is warned about.
TUMOUR_HINT_SLACK_MM = 5.0


#: Below this match confidence the tracked tumour's identity in a scan is ambiguous (warned).
TUMOUR_MIN_CONFIDENCE = 0.95
#: Standard deviation of one inclusion diameter measurement, mm: the same inclusion measured
#: in two postures of the digital twin differs by 0.3-0.4 mm rms at 1.5-2 mm voxels.
SIZE_SD_MM = 0.3
#: The largest voxel edge up to which :data:`SIZE_SD_MM` was measured, mm.
SIZE_SD_VOXEL_MM = 2.0


def size_sd_mm(*voxel_sizes_mm) -> float:
    """Standard deviation of an inclusion diameter measured on voxels of these sizes (mm).

    :data:`SIZE_SD_MM` up to :data:`SIZE_SD_VOXEL_MM` voxels (as measured on the twin),
    in proportion to the largest voxel edge beyond (a diameter's partial-volume error
    scales with the voxel: thick slices must not make the size match overconfident).

    Parameters
    ----------
    *voxel_sizes_mm : array_like, shape (3,)
        The scans' voxel sizes.

    Returns
    -------
    float
    """
    edge = max((float(np.max(v)) for v in voxel_sizes_mm), default=0.0)
    return SIZE_SD_MM * max(1.0, edge / SIZE_SD_VOXEL_MM)


@dataclass(frozen=True)
class InclusionTracking:
    """Identity of every inclusion of one scan among the reference scan's inclusions.

    Attributes
    ----------
    reference_index : tuple of (int or None)
        Per inclusion of this scan (in its ``inclusions`` order), the index of the
        reference scan's inclusion it is, or None (no match: a missed or extra detection).
    confidence : tuple of float
        Per inclusion, the confidence of that identity
        (:data:`registration.CONFIDENCE_DEFINITION`); 1 in the reference scan.
    tumour_index : int or None
        This scan's inclusion that is the tracked tumour, or None (not found here).
    tumour_confidence : float or None
        Confidence of the tracked tumour's identity in this scan.
    runner_up_index : int or None
        The inclusion the tumour would be in the best competing assignment (None: none).
    hypothesis : str
        The initial map the matching started from (``reference`` for the reference scan).
    field_checked : bool
        Whether the match was weighed against a deformation field
        (:attr:`registration.ConstellationMatch.field_checked`; False for one or two
        inclusions: the confidences then do not mean what they say).
    """

    reference_index: tuple
    confidence: tuple
    tumour_index: int | None
    tumour_confidence: float | None
    runner_up_index: int | None
    hypothesis: str
    field_checked: bool = True

    def to_json(self) -> dict:
        """JSON-ready summary (``tracking`` of ``ingest.json``, without the per-inclusion lists)."""
        return {
            "tumour_index": self.tumour_index,
            "tumour_confidence": self.tumour_confidence,
            "tumour_runner_up_index": self.runner_up_index,
            "hypothesis": self.hypothesis,
            "field_checked": self.field_checked,
        }


@dataclass(frozen=True)
class TumourChoice:
    """The tracked tumour in the reference scan: its inclusion index and why it was chosen."""

    reference_index: int | None
    reason: str


def _choose_tumour(session: Session, res) -> TumourChoice:
    """The reference scan's tracked inclusion: nearest to the hint, else the largest."""
    import imaging

    c, d = res.inclusions.centres_lps_mm, res.inclusions.diameters_mm
    if len(c) == 0:
        if session.tumour_hint_lps_mm is not None:  # review BG: dropped without a word
            import warnings

            warnings.warn(
                f"{session.reference.name!r}: no inclusion found in the reference scan, so "
                "the [landmarks] tumour hint is not used (ingest finds bright inclusions "
                "2-15 mm wide); no tumour is tracked",
                TumourHintWarning,
                stacklevel=2,
            )
        return TumourChoice(None, "no inclusion found in the reference scan")
    k = imaging.select_tumour(c, d, hint_lps_mm=session.tumour_hint_lps_mm)
    if session.tumour_hint_lps_mm is not None:
        dist = np.sort(np.linalg.norm(c - session.tumour_hint_lps_mm, axis=1))
        other = f"; the next nearest is {dist[1]:.1f} mm away" if len(dist) > 1 else ""
        if dist[0] > 0.5 * d[k] + TUMOUR_HINT_SLACK_MM:
            import warnings

            warnings.warn(
                f"{session.reference.name!r}: the inclusion nearest the [landmarks] tumour "
                f"hint is {dist[0]:.1f} mm from it ({d[k]:.1f} mm wide): the tumour itself "
                "may not be segmented (ingest finds bright inclusions 2-15 mm wide); it is "
                "tracked all the same",
                TumourHintWarning,
                stacklevel=2,
            )
        return TumourChoice(
            k, f"nearest to the [landmarks] tumour hint ({dist[0]:.1f} mm away{other})"
        )
    why = f"the largest inclusion ({d[k]:.1f} mm; no [landmarks] tumour hint in session.toml"
    if len(d) > 1:
        second = float(np.sort(d)[-2])
        why += f"; the next largest is {second:.1f} mm"
        if d[k] - second < 2.0 * np.sqrt(2.0) * size_sd_mm(res.voxel_size_mm):
            why += ", within the measurement noise: set [landmarks] tumour to choose"
    return TumourChoice(k, why + ")")


def _describe(res, j: int | None, T) -> str:
    if j is None or j < 0:
        return "no inclusion (unmatched)"
    p = apply_transform(T, res.inclusions.centres_lps_mm[j])
    return (
        f"inclusion {j} (diameter {res.inclusions.diameters_mm[j]:.1f} mm, at "
        f"[{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}] mm in the reference frame)"
    )


def _track_inclusions(session: Session, scans: dict, fiducial_regs: dict, choice: TumourChoice):
    """Every scan's inclusions matched to the reference scan's, as one constellation.

    :func:`registration.match_constellation` with the inclusion diameters as sizes, the
    nipple as an anchor and the reference back plane (the inclusions mapped into the
    reference frame by the fiducial registration). A tracked tumour matched with a
    confidence below :data:`TUMOUR_MIN_CONFIDENCE` is an
    :class:`registration.AmbiguousMatchWarning` naming the scan and the candidates; one
    with no match a :class:`TumourNotFoundWarning`.
    """
    import warnings

    from registration import AmbiguousMatchWarning, match_constellation

    ref = session.reference.name
    r = scans[ref]
    X, dX = r.inclusions.centres_lps_mm, r.inclusions.diameters_mm
    t = choice.reference_index
    out = {
        ref: InclusionTracking(
            tuple(range(len(X))), (1.0,) * len(X), t, None if t is None else 1.0, None, "reference"
        )
    }
    plane = (r.back_plane.point_lps_mm, r.back_plane.normal)
    for name, res in scans.items():
        if name == ref:
            continue
        T = fiducial_regs[name].T_ref_from_scan
        Y = apply_transform(T, res.inclusions.centres_lps_mm)
        nipple = apply_transform(T, res.nipple_lps_mm)[None]
        m = match_constellation(
            X,
            dX,
            Y,
            res.inclusions.diameters_mm,
            anchors_reference_mm=r.nipple_lps_mm[None],
            anchors_mm=nipple,
            base_plane=plane,
            size_sd_mm=size_sd_mm(r.voxel_size_mm, res.voxel_size_mm),
        )
        ident = tuple(None if i < 0 else int(i) for i in m.reference_index)
        conf = tuple(float(c) for c in m.confidence)
        j = tc = alt = None
        if t is not None:
            j = None if m.scan_index[t] < 0 else int(m.scan_index[t])
            tc = float(m.reference_confidence[t])
            alt = None if m.reference_runner_up[t] < 0 else int(m.reference_runner_up[t])
            tumour = f"the tracked tumour (reference inclusion {t}, {dX[t]:.1f} mm)"
            if j is None and len(Y) == 0:
                warnings.warn(
                    f"scan {name!r}: no inclusion found, so not {tumour}; its "
                    "tumour_lps_mm is left unset",
                    TumourNotFoundWarning,
                    stacklevel=3,
                )
            elif j is None:
                near = np.argsort(np.linalg.norm(Y - m.predicted_mm[t], axis=1))[:2]
                warnings.warn(
                    f"scan {name!r}: {tumour} matches no inclusion (confidence {tc:.2f}); "
                    f"expected near [{', '.join(f'{v:.1f}' for v in m.predicted_mm[t])}] mm "
                    f"(reference frame); nearest candidates: "
                    + "; ".join(_describe(res, int(k), T) for k in near)
                    + "; its tumour_lps_mm is left unset",
                    TumourNotFoundWarning,
                    stacklevel=3,
                )
            elif not m.field_checked:
                moved = float(np.linalg.norm(Y[j] - X[t]))
                nipple_moved = float(np.linalg.norm(nipple[0] - r.nipple_lps_mm))
                warnings.warn(
                    f"scan {name!r}: {tumour} tracked as {_describe(res, j, T)}, "
                    f"{moved:.1f} mm from its reference position (the nipple moved "
                    f"{nipple_moved:.1f} mm), by size and the nipple alone: "
                    f"{int((m.reference_index >= 0).sum())} inclusion(s) matched are too few "
                    "to fit a deformation field, so a missed tumour is not weighed against "
                    f"another inclusion and its confidence ({tc:.2f}) does not mean what it "
                    "says. Check this scan's tumour",
                    AmbiguousMatchWarning,
                    stacklevel=3,
                )
            elif tc < TUMOUR_MIN_CONFIDENCE:
                rivals = [(k, p) for k, p in m.reference_alternatives[t] if p >= 0.01] or [
                    (-1 if alt is None else alt, 1.0 - tc)
                ]
                listing = "; ".join(f"{_describe(res, k, T)}: {p:.2f}" for k, p in rivals)
                warnings.warn(
                    f"scan {name!r}: ambiguous match of {tumour}: tracked as "
                    f"{_describe(res, j, T)} with confidence {tc:.2f}; competing "
                    f"candidates (probability against the tracked one): {listing}. Check "
                    "this scan's tumour (every inclusion's match_confidence is in its "
                    "ingest.json)",
                    AmbiguousMatchWarning,
                    stacklevel=3,
                )
        low = [k for k, c in enumerate(conf) if c < TUMOUR_MIN_CONFIDENCE]
        if low:
            log.info(
                "scan %s: inclusions %s matched with confidence < %.2f",
                name,
                low,
                TUMOUR_MIN_CONFIDENCE,
            )
        out[name] = InclusionTracking(ident, conf, j, tc, alt, m.hypothesis, m.field_checked)
    return out


def _tracking_table(choice: TumourChoice, tracking: dict) -> str:
    """Plain-text lines on the tracked tumour and every scan's inclusion identities."""
    head = (
        "tracked tumour: none"
        if choice.reference_index is None
        else f"tracked tumour: reference inclusion {choice.reference_index}, {choice.reason}"
    )
    rows = [
        (
            "scan",
            "inclusions",
            "matched",
            "tumour inclusion",
            "tumour confidence",
            "lowest confidence",
        )
    ]
    for name, tr in tracking.items():
        matched = sum(i is not None for i in tr.reference_index)
        rows.append(
            (
                name,
                str(len(tr.reference_index)),
                str(matched),
                "-" if tr.tumour_index is None else str(tr.tumour_index),
                "-" if tr.tumour_confidence is None else f"{tr.tumour_confidence:.3f}",
                f"{min(tr.confidence):.3f}" if tr.confidence else "-",
            )
        )
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    lines = [
        "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in rows
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join([head, *lines])


def _with_tumour(res, i: int | None):
    if i is None:
        return replace(res, tumour_lps_mm=None)
    return replace(res, tumour_lps_mm=res.inclusions.centres_lps_mm[i])


def _register(session: Session, scans: dict, landmarks: bool):
    import registration
    from fem.postures import gravity_for_angle

    fids = {n: r.fiducials_lps_mm for n, r in scans.items()}
    nominal = {  # in the nominal phantom frame: only the angles between them are checked
        s.name: gravity_for_angle(s.posture_angle_deg, plane=s.posture_plane or "transverse")
        for s in session.scans
        if s.posture_angle_deg is not None
    }
    marks = None
    if landmarks:
        marks = {
            n: {"nipple": r.nipple_lps_mm}
            | ({"tumour": r.tumour_lps_mm} if r.tumour_lps_mm is not None else {})
            for n, r in scans.items()
        }
    # the first pass (without landmarks, for the inclusion tracking) is said by the second:
    # its lines and warnings were printed twice (review AX)
    quiet = logging.getLogger("registration")
    level = quiet.level
    if not landmarks:
        quiet.setLevel(logging.ERROR)
    try:
        return registration.register_scans(
            fids,
            reference=session.reference.name,
            gravity_scanner=session.gravity_scanner,
            nominal_gravity=nominal if len(nominal) >= 2 else None,
            landmarks_by_scan=marks,
            plate_normals_by_scan={n: r.back_plane.normal for n, r in scans.items()},
            footprints_by_scan=_footprints(scans),
        )
    finally:
        quiet.setLevel(level)


def _footprints(scans: dict) -> dict:
    """Per scan its back-plate patch: ``(vertices (k, 3) LPS mm, faces (f, 3))``.

    The faces whose three vertices are flagged ``back_plate``; a scan with fewer than 10
    such faces, its flagged vertices alone ((k, 3): compared point to point). Scans with
    fewer than 10 flagged vertices (no flags, no flat face) have none, nor then any scan.
    """
    out = {}
    for name, r in scans.items():
        flags = r.surface.back_plate
        if flags is None or np.count_nonzero(flags) < 10:
            return {}
        flags = np.asarray(flags, bool)
        faces = r.surface.faces[flags[r.surface.faces].all(axis=1)]
        if len(faces) < 10:
            out[name] = r.surface.vertices_lps_mm[flags]
            continue
        used, faces = np.unique(faces, return_inverse=True)
        out[name] = (r.surface.vertices_lps_mm[used], faces.reshape(-1, 3))
    return out


def _check_patient_positions(session: Session) -> None:
    """Warn where the DICOM scans were written in different patient positions.

    ``scanner.gravity`` is one vector in every scan's image coordinates; DICOM's patient
    coordinates turn with PatientPosition (``HFS`` to ``HFP`` flips y and x), so scans
    written in different positions see gravity in different directions.
    """
    from imaging.dicom import patient_position

    found = {s.name: patient_position(s.path) for s in session.scans if s.path.is_dir()}
    if len({p for p in found.values() if p is not None}) > 1:
        said = ", ".join(f"{n}: {p or 'none'}" for n, p in found.items())
        log.warning(
            "%s: the DICOM scans were written in different patient positions (%s); "
            "scanner.gravity is read in every scan's image coordinates, which turn with "
            "the patient position: check that gravity is the same vector in all of them",
            session.folder / "session.toml",
            said,
        )


#: A scan's nipple must move this far (mm) from the reference scan's, and its gravity turn
#: this far (degrees) from the reference's, for the direction of the move to count: well
#: over the nipple's own localisation error (1.6-1.8 mm on the quick twin, review AF), so
#: one posture's move cannot turn round by it alone (the quick twin: 33 and 7.3 mm count,
#: the 25 degree scan's 2.5 mm does not).
SAG_CHECK_MM, SAG_CHECK_DEG = 5.0, 10.0


def check_gravity_sign(session: Session, scans: dict, regs: dict) -> dict[str, float]:
    """Warn where the nipple moved against the change of gravity in every posture.

    A soft body sags with gravity: between two postures its nipple moves along the
    change of the gravity vector (the quick twin: cosines +1.00, +0.87, +0.82). A
    ``scanner.gravity`` of the wrong sign (the default ``[0, 1, 0]``, +P, is down for a
    supine image; breast MR is often written prone, where down is -P) turns every cosine
    negative, which no other check sees (the posture check compares angles between
    scans, which a sign flip keeps; review AE).

    Parameters
    ----------
    session : Session
    scans : dict of str to imaging.ScanResult
    regs : dict of str to registration.ScanRegistration

    Returns
    -------
    dict of str to float
        Per scan whose nipple moved over :data:`SAG_CHECK_MM` and whose gravity turned
        over :data:`SAG_CHECK_DEG` from the reference's, the cosine between the two moves.
    """
    ref = session.reference.name
    nipple_ref = scans[ref].nipple_lps_mm
    cosines = {}
    for name, reg in regs.items():
        if name == ref:
            continue
        move = apply_transform(reg.T_ref_from_scan, scans[name].nipple_lps_mm) - nipple_ref
        turn = reg.gravity_ref - regs[ref].gravity_ref
        if np.linalg.norm(move) < SAG_CHECK_MM:
            continue
        if np.linalg.norm(turn) < 2.0 * np.sin(np.radians(SAG_CHECK_DEG) / 2.0):
            continue
        cosines[name] = float(move @ turn / np.linalg.norm(move) / np.linalg.norm(turn))
    if cosines and all(c < 0 for c in cosines.values()):
        log.warning(
            "%s: in every posture the nipple moved against the change of gravity (cosines "
            "%s between its move and gravity's, from the reference scan): a body sags with "
            "gravity, so scanner.gravity %s likely points up; an image written prone has "
            "down at -P ([0, -1, 0] where a supine one has [0, 1, 0])",
            session.folder / "session.toml",
            ", ".join(f"{n} {c:+.2f}" for n, c in cosines.items()),
            np.round(session.gravity_scanner, 3).tolist(),
        )
    return cosines


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
    _check_patient_positions(session)
    scans = {s.name: _process(s, session, tick) for s in session.scans}
    regs = _register(session, scans, landmarks=False)
    choice = _choose_tumour(session, scans[session.reference.name])
    tracking = _track_inclusions(session, scans, regs, choice)
    tumour = {n: tr.tumour_index for n, tr in tracking.items()}
    scans = {n: _with_tumour(r, tumour[n]) for n, r in scans.items()}
    regs = _register(session, scans, landmarks=True)
    check_gravity_sign(session, scans, regs)
    table = registration.format_registration_table(
        regs, roles={s.name: s.role for s in session.scans}
    )
    table += "\n\n" + _tracking_table(choice, tracking)
    return IngestResult(session, scans, regs, tumour, table, tracking, choice)


def load_ingest(work: str | Path, name: str) -> dict:
    """Read ``work/scans/<name>/ingest.json``."""
    path = Path(work) / "scans" / name / "ingest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: run `phantom-calib ingest` first")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(
            f"{path}: not valid JSON ({exc}); run `phantom-calib ingest` again"
        ) from exc
    if not isinstance(doc, dict):
        raise ValueError(
            f"{path}: expected a JSON object (ingest's record), got {type(doc).__name__}; "
            "run `phantom-calib ingest` again"
        )
    return doc


class StaleIngestError(RuntimeError):
    """The ingest results in a work folder are not those of the current scans."""


#: Revision of what ingest makes of the same scans; results of another revision are stale.
#: 1 (no ``ingest_revision`` recorded): before the flags of a cut field of view. 2: those
#: flags (``fov_edge``), at most 1.5 mm^2 per surface face, the back face found below a
#: lip hanging more than 10 mm past the plate's edge, the fiducials' plane given way to a
#: face that rises more than 0.75 mm over it. 3: the surface's largest plane refined by
#: least squares on its band (RANSAC's plane tilted within it: the fiducials' plane was set
#: aside for a face 0.41 degrees off the truth). 4: the bias field's degree along an axis
#: the body spans in few slices, markers apart from the body down to 1.3 times its level,
#: the back plane's voxel depth (``back_plane.voxel_depth_mm``, the clamped face's
#: tolerance on thick slices). 5: a nipple bump looked for over the body's upper half
#: where none stands within 12 mm of the highest point (``quality.nipple_method``), and
#: the regions too large for an inclusion counted (``quality.inclusions_too_large``). 6:
#: the image noise (``quality.seg_noise_sigma_rel``, ``seg_snr``) from the background's
#: median (its mean of squares took in the markers: up to a third too high). 7: a bright
#: blob that tissue encloses is an inclusion, never a marker, and stays in the body mask
#: (inclusions over twice the body's level were counted as markers and cut from the body);
#: the image noise from the body's interior where the background is no Rayleigh floor
#: (``quality.seg_noise_method``). 8: that interior noise at the lag where correlated
#: neighbours (an interpolated image) stop reading it low. 9: the segmentation made again
#: from the bias-corrected body where it reached its crop (``quality.seg_crop_passes``),
#: far markers looked for on the corrected image too, the bias spread measured over the
#: body found; an inclusion's extreme near the surface left out as a skin's tail only
#: where the contrast rises towards the surface (``quality.inclusions_surface_layer``).
INGEST_REVISION = 9


def ingest_inputs(session: Session) -> dict:
    """Fingerprints of what ingest reads, and its :data:`INGEST_REVISION`.

    The session (:meth:`Session.ingest_fingerprint`) and every scan's source
    (:func:`calib.io.source_sha256`).
    """
    from ..io import source_sha256

    return {
        "session_sha256": session.ingest_fingerprint(),
        "sources_sha256": {s.name: source_sha256(s.path) for s in session.scans},
        "ingest_revision": INGEST_REVISION,
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
    revision = recorded.get("ingest_revision", 1)
    if revision != INGEST_REVISION:
        reasons.append(
            f"the ingest results are of an older phantom-calib (ingest revision {revision}, "
            f"now {INGEST_REVISION}: the scans may give other surfaces and flags)"
        )
    # ingest results written before 2026-12-07 fingerprinted the scans' absolute paths
    legacy = session.ingest_fingerprint(paths="absolute")
    if recorded["session_sha256"] not in (now["session_sha256"], legacy):
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
