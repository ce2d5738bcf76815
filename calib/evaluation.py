"""Per-scan results of a calibrated model: surface, nipple and tumour errors (no I/O).

:func:`scan_metrics` measures one simulated posture against its scan from positions
alone (so saved deformed states can be re-measured without FE, :mod:`calib.validation`);
:func:`evaluate` solves the postures at the calibrated c1 and measures them;
:func:`check_postures` asks whether every scan, fitted alone, would give the same c1
(:mod:`calib.stats.consistency`), the second half of ``calibration.json``'s ``model_fit``.

Frames (as in the dissertation, ch. 3.4): ``fiducial`` maps the scan by the fiducial
registration only; ``icp`` adds a rigid ICP of the measured surface onto the simulated
one, which absorbs part of the model error: its surface error is biased low, while the
nipple and tumour errors may rise or fall.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

import fem

from .data.measurements import Measurements, ScanMeasurement
from .stats.consistency import POSTURE_ALPHA, PostureConsistency
from .stats.intervals import MIN_SERIES_POINTS, _json_number

__all__ = [
    "POSTURE_ALPHA",
    "EvaluationError",
    "ScanEvaluation",
    "ScanMetrics",
    "check_postures",
    "evaluate",
    "model_fit_with_postures",
    "scan_metrics",
    "scan_names",
]

log = logging.getLogger(__name__)


class EvaluationError(ValueError):
    """A Calibration, scan names or evaluations that cannot be evaluated as asked.

    The message says what was given and what to pass instead.
    """


#: Spacing of the simulated surface's samples that ICP aligns the scan to (mm): the finest
#: of :func:`registration.icp_refine`'s correspondence gates.
ICP_TARGET_SPACING_MM = 1.0


@dataclass(frozen=True)
class ScanMetrics:
    """Errors of one simulated posture against its scan.

    Attributes
    ----------
    nipple_error_mm : dict of str to float
        The dissertation's nipple error (closest measured surface point to the simulated
        nipple), by frame.
    nipple_landmark_error_mm : float
        Simulated nipple node to the measured nipple landmark, fiducial frame.
    surface_error_mm : dict of str to dict
        By frame: ``mean``, ``sd``, ``median``, ``p95``, ``max``, ``n`` of the absolute
        distances of the measured surface points (off the back plate) to the simulated
        surface.
    tumour_error_mm : dict of str to float or None
        Simulated to measured tumour centre, by frame (None without a tumour).
    icp : dict
        ``fitness`` and ``inlier_rmse_mm`` of the ICP, ``converged``, the size of its
        ``rotation_deg`` and ``translation_mm``, and ``target_spacing_mm`` (the simulated
        surface is sampled that finely as its target).
    T_sim_from_measured : ndarray, shape (4, 4)
        ICP transform, measured points -> simulated surface (``T_icp``, its former name,
        reads it too).
    vertex_error_mm : ndarray, shape (n_vertices,)
        Signed distance of every measured vertex to the simulated surface, fiducial frame
        (0 on the back plate, which is not compared).
    """

    nipple_error_mm: dict
    nipple_landmark_error_mm: float
    surface_error_mm: dict
    tumour_error_mm: dict | None
    icp: dict
    T_sim_from_measured: np.ndarray
    vertex_error_mm: np.ndarray

    @property
    def T_icp(self) -> np.ndarray:
        """Former name of :attr:`T_sim_from_measured`."""
        return self.T_sim_from_measured

    def to_json(self) -> dict:
        """The per-scan error block of ``calibration.json``."""
        out = {
            "nipple_error_mm": self.nipple_error_mm,
            "nipple_landmark_error_mm": {"fiducial": self.nipple_landmark_error_mm},
            "surface_error_mm": self.surface_error_mm,
            "icp": self.icp,
        }
        if self.tumour_error_mm is not None:
            out["tumour_error_mm"] = self.tumour_error_mm
        return out


def _summary(s) -> dict:
    return {
        "mean": s.mean_mm,
        "sd": s.sd_mm,
        "median": s.median_mm,
        "p95": s.p95_mm,
        "max": s.max_mm,
        "n": s.n,
    }


def scan_metrics(
    scan: ScanMeasurement,
    positions_mm: np.ndarray,
    faces: np.ndarray,
    nipple_node: int,
    tumour_mm: np.ndarray | None = None,
) -> ScanMetrics:
    """Measure a simulated posture against its scan.

    Parameters
    ----------
    scan : ScanMeasurement
        The measured scan (reference frame, mm).
    positions_mm : ndarray, shape (n_nodes, 3)
        Simulated (deformed) vertex positions of the model mesh, reference frame.
    faces : ndarray, shape (f, 3)
        The model's outer surface without its back face (``SimulatedSurface.faces``).
    nipple_node : int
        The model's nipple vertex.
    tumour_mm : ndarray, shape (3,), optional
        The simulated tumour centre.
    """
    import registration

    pos = np.asarray(positions_mm, float)
    pts = scan.vertices_mm[scan.scored]
    # the simulated surface where it is, not at its vertices alone (a coarse model's are
    # ~12 mm apart: the 2 and 1 mm gates found 3-4 % of the scan, and ICP never settled)
    target, normals = registration.sample_triangles(pos, faces, spacing_mm=ICP_TARGET_SPACING_MM)
    icp = registration.icp_refine(pts, target, target_normals=normals)
    T = icp.T_target_from_source
    if not icp.settled:  # review AO: not icp.converged warned on a round body's creep
        log.warning(
            "scan %r: ICP of the measured onto the simulated surface did not settle within "
            "%s iterations per level: its 'icp' frame figures are not at a minimum",
            scan.name,
            icp.iterations,
        )
    T_inv = np.linalg.inv(T)
    surf = registration.surface_errors(
        pts, pos, faces, frames=("fiducial", "icp"), T_fixed_from_moving=T
    )
    # the measured surface without a cut field of view's edge (the back plate stays:
    # it is surface, though far from the nipple)
    nipple = registration.nipple_error(
        pos[nipple_node],
        scan.vertices_mm[scan.in_view],
        frames=("fiducial", "icp"),
        T_fixed_from_moving=T_inv,
    )
    tumour = None
    if tumour_mm is not None and scan.tumour_mm is not None:
        tumour = {
            "fiducial": float(np.linalg.norm(tumour_mm - scan.tumour_mm)),
            "icp": float(
                np.linalg.norm(registration.apply_transform(T_inv, tumour_mm) - scan.tumour_mm)
            ),
        }
    vertex_error = np.zeros(len(scan.vertices_mm))
    vertex_error[scan.scored] = surf["fiducial"].distances_mm
    return ScanMetrics(
        nipple_error_mm={f: e.error_mm for f, e in nipple.items()},
        nipple_landmark_error_mm=float(np.linalg.norm(pos[nipple_node] - scan.nipple_mm)),
        surface_error_mm={f: _summary(e.summary) for f, e in surf.items()},
        tumour_error_mm=tumour,
        icp={
            "fitness": icp.fitness,
            "inlier_rmse_mm": icp.inlier_rmse_mm,
            "converged": icp.converged,
            "settled": icp.settled,
            "rotation_deg": float(
                np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
            ),
            "translation_mm": float(np.linalg.norm(T[:3, 3])),
            "target_spacing_mm": ICP_TARGET_SPACING_MM,
        },
        T_sim_from_measured=T,
        vertex_error_mm=vertex_error,
    )


@dataclass(frozen=True)
class ScanEvaluation:
    """A scan at the calibrated c1: the simulated state and its errors.

    Attributes
    ----------
    name, role : str
    gravity_ref : ndarray, shape (3,)
    positions_mm : ndarray, shape (n_nodes, 3) or None
        Simulated vertex positions (None when the FE solve failed).
    dpositions_mm : ndarray, shape (n_nodes, 3) or None
        Their derivative in ln c1 (mm per unit ln c1), for intervals of every error.
    tumour_mm, dtumour_mm : ndarray, shape (3,) or None
        Simulated tumour centre and its derivative in ln c1.
    metrics : ScanMetrics or None
    failed : str or None
        Why there is no FE solution at the calibrated c1.
    posture : dict or None
        The session's nominal posture (``plane``, ``angle_deg``; None where not given).
    """

    name: str
    role: str
    gravity_ref: np.ndarray
    positions_mm: np.ndarray | None
    dpositions_mm: np.ndarray | None
    tumour_mm: np.ndarray | None
    dtumour_mm: np.ndarray | None
    metrics: ScanMetrics | None
    failed: str | None = None
    posture: dict | None = None

    def to_json(self) -> dict:
        """The scan's block of ``calibration.json`` (``scans.<name>``)."""
        out = {"role": self.role, "gravity_ref": self.gravity_ref.tolist(), "posture": self.posture}
        if self.failed is not None:
            return out | {"failed": self.failed}
        return out | self.metrics.to_json()


def scan_names(scans, known: dict) -> list[str]:
    """The scan names a caller asked for: None is every scan but the reference.

    A single name may be given as a string (review AI: ``scans="tilt_25"`` was taken letter
    by letter, and ``[]`` for every scan).

    Raises
    ------
    EvaluationError
        An empty list, or names not in ``known`` (a ``ValueError``).
    """
    if scans is None:
        return [n for n, s in known.items() if s.role != "reference"]
    if not isinstance(scans, str) and not hasattr(scans, "__iter__"):  # review AU: 3
        raise TypeError(f"scans must be a scan name or names, got {scans!r}")
    names = [scans] if isinstance(scans, str) else list(scans)
    if not names:
        raise EvaluationError("no scan named: pass scan names, or None for every scan")
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise EvaluationError(f"unknown scan(s) {unknown}; the session has {sorted(known)}")
    return names


def _calibrator(calibration, what: str):
    """The live model of a :class:`calib.fitting.Calibration`; a clear error for anything else.

    Review AU: a work folder's path or ``calib.load_work``'s object ended in an
    AttributeError from deep inside.
    """
    if not hasattr(calibration, "calibrator"):
        raise TypeError(
            f"{what} takes the Calibration that calib.fit returns, got "
            f"{type(calibration).__name__}; a work folder's figures: calib.load_work(...), "
            "calib.validate(...)"
        )
    return calibration.calibrator


def evaluate(
    calibration,
    measurements: Measurements | None = None,
    *,
    scans: str | list[str] | None = None,
    gradient: bool = True,
) -> dict[str, ScanEvaluation]:
    """Solve every scan's posture at the calibrated c1 and measure it.

    Parameters
    ----------
    calibration : Calibration
        The result of :func:`calib.fit`.
    measurements : Measurements, optional
        Defaults to the measurements the calibration was fitted to.
    scans : str or list of str, optional
        A scan name or names; default every scan but the reference.
    gradient : bool
        Also the derivatives in ln c1 (one more factorisation per scan).

    Returns
    -------
    dict of str to ScanEvaluation
        A scan whose FE solve fails at the calibrated c1 has ``failed`` set (and a
        warning is logged), the others are evaluated regardless.

    Raises
    ------
    TypeError
        ``calibration`` is not a Calibration.
    EvaluationError
        A Calibration without its model (from JSON), an unknown scan name or an empty
        list of names (a ``ValueError``).
    """
    cal = _calibrator(calibration, "evaluate")
    if cal is None:
        raise EvaluationError(
            "this Calibration carries no calibrator (the model to solve): evaluate takes the "
            "result of calib.fit"
        )
    meas = measurements or cal.measurements
    names = scan_names(scans, meas.scans)
    nipple = int(cal.mesh.node_set("nipple")[0])
    theta = calibration.theta
    out = {}
    for name in names:
        scan = meas.scans[name]
        head = (name, scan.role, scan.gravity_ref)
        try:
            st = cal.fm.evaluate(theta, {name: scan.gravity_ref}, gradient=gradient)[name]
        except fem.ConvergenceError as exc:
            log.warning("scan %s: no FE solution at the calibrated c1 (%s)", name, exc)
            out[name] = ScanEvaluation(
                *head, *(None,) * 5, failed=str(exc), posture=scan.nominal_posture
            )
            continue
        tumour = cal.tumour_position(st, gradient)
        t, dt = (None, None) if tumour is None else tumour
        metrics = scan_metrics(scan, st.positions_mm, cal.sim.faces, nipple, t)
        out[name] = ScanEvaluation(
            *head, st.positions_mm, st.dpositions_mm, t, dt, metrics, posture=scan.nominal_posture
        )
    return out


#: Fewest surface residuals of a scan for its own estimate (as the series interval).
MIN_SCAN_POINTS = MIN_SERIES_POINTS
#: A scan whose residual's c1 derivative (centred: each scan's own fit takes its offset)
#: is below this share of the strongest scan's, RMS over its points, carries no c1 of its
#: own (a repeat of the reference posture): its weight in Cochran's Q would be < 1e-4 of
#: that scan's, and its own estimate round-off. It is left out of the posture test.
MIN_POSTURE_SENSITIVITY_SHARE = 0.01


def check_postures(
    calibration, evaluations: dict, *, alpha: float = POSTURE_ALPHA
) -> tuple[PostureConsistency, dict[int, str]] | None:
    """Posture consistency of a surface calibration: every solved scan's own c1.

    The residual of every scan with an FE solution (calibration and validation) at the
    calibrated c1, on the calibration's seeded surface points, is tested by
    :func:`calib.stats.consistency.posture_consistency` under the session's noise model
    (its default). No FE solve: the states and their ln c1 derivatives are :func:`evaluate`'s.

    Parameters
    ----------
    calibration : Calibration
        The result of :func:`calib.fit` (with its calibrator).
    evaluations : dict of str to ScanEvaluation
        From :func:`evaluate` with ``gradient=True``.
    alpha : float
        False-alarm rate of the verdict, in (0, 1)
        (:data:`calib.stats.consistency.POSTURE_ALPHA` by default).

    Returns
    -------
    tuple of (PostureConsistency, dict of int to str) or None
        The test and the scan name of each label; None for an objective other than
        ``surface``, or when fewer than two scans have a solution, at least
        ``MIN_SCAN_POINTS`` surface points and a surface that changes with c1
        (``MIN_POSTURE_SENSITIVITY_SHARE``; a scan left out is warned about).

    Raises
    ------
    TypeError
        ``calibration`` is not the :class:`Calibration` that :func:`calib.fit` returns.
    EvaluationError
        A solved scan evaluated without its derivative (``gradient=False``; a
        ``ValueError``).
    calib.stats.consistency.ConsistencyError
        ``alpha`` outside (0, 1), whatever the scans (review BJ: it was found only once
        two scans were tested); a scan whose c1 estimate has no interval (a
        ``ValueError``).
    """
    from .model.reference import scale_of
    from .model.residuals import scan_residuals
    from .stats import SurfaceSample
    from .stats.consistency import ConsistencyError, posture_consistency
    from .stats.noise import MAX_LAG_MM

    if not 0.0 < alpha < 1.0:
        raise ConsistencyError(f"alpha must lie in (0, 1), got {alpha}")
    cal = _calibrator(calibration, "check_postures")
    if cal is None or calibration.objective != "surface":
        return None
    rs, js, pts, labels, names, found = [], [], [], [], {}, []
    for name, ev in evaluations.items():
        if ev.failed is not None:
            continue
        if ev.dpositions_mm is None:  # review AI: this returned None, as "no test applies"
            raise EvaluationError(
                f"scan {name} was evaluated without its derivative in ln c1, which the "
                "posture test needs: evaluate(calibration, gradient=True)"
            )
        res = scan_residuals(
            "surface",
            cal.measurements.scans[name],
            cal.mesh,
            cal.sim,
            ev.positions_mm,
            ev.dpositions_mm,
            surface_points_mm=cal.points[name],
        )
        if len(res.r) < MIN_SCAN_POINTS:
            continue
        found.append((name, res, float(np.sqrt(np.mean((res.dr - res.dr.mean()) ** 2)))))
    strongest = max((f[2] for f in found), default=0.0)
    for name, res, sensitivity in found:
        if not sensitivity > MIN_POSTURE_SENSITIVITY_SHARE * strongest:
            log.warning(
                "scan %r: its surface barely changes with c1 (%.2g of the most sensitive "
                "scan's; the reference posture again?): left out of the posture test",
                name,
                sensitivity / strongest if strongest > 0 else 0.0,
            )
            continue
        names[len(rs)] = name
        labels.append(np.full(len(res.r), len(rs)))
        rs.append(res.r)
        js.append(res.dr)
        pts.append(res.points_mm)
    if len(rs) < 2:
        return None
    sample = SurfaceSample(np.concatenate(pts), np.concatenate(labels))
    test = posture_consistency(
        calibration.theta,
        np.concatenate(rs),
        np.concatenate(js),
        sample,
        alpha=alpha,
        seed=cal.options.seed,
        # review BN N4: the variogram's reach scales with the body, as calibrate's
        max_lag_mm=MAX_LAG_MM * scale_of(cal.measurements.reference),
    )
    return test, names


def _c1_pa(theta) -> float | None:
    """c1 in Pa of ``theta = ln c1`` as JSON writes it (None where either is not finite)."""
    if theta is None:
        return None
    with np.errstate(over="ignore"):
        return _json_number(np.exp(theta))


def model_fit_with_postures(model_fit: dict | None, postures, names: dict) -> dict | None:
    """``calibration.json``'s ``model_fit`` with the posture test added.

    The band-F fields stay as they were (``statistic``, ``p_value``, ``alpha``: the
    band-F test's; its own verdict is ``band_f_verdict``); ``postures`` holds the
    posture test; ``verdict`` is ``misfit`` when either test fires. The test's parameter
    ``theta`` is ln c1 (c1 in Pa): each scan's estimate and their mean are also given as
    ``c1_pa`` and ``c1_bar_pa`` (review BE: ``theta`` alone read as an angle).
    """
    if postures is None:
        return model_fit
    out = dict(model_fit or {})
    band = out.get("verdict")
    out["band_f_verdict"] = band
    doc = postures.as_json(names)
    doc["c1_bar_pa"] = _c1_pa(doc["theta_bar"])
    for scan in doc["scans"].values():
        scan["c1_pa"] = _c1_pa(scan["theta"])
    out["postures"] = doc
    out["verdict"] = "misfit" if band == "misfit" or postures.verdict == "inconsistent" else "fits"
    return out
