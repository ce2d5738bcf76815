"""The result of a calibration: a frozen :class:`Calibration` and its JSON form."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

import numpy as np

from ..data.work import SCHEMA_VERSION
from ..model.reference import MIN_ELEMENTS_IN_HEIGHT
from .meshcheck import MeshCheck
from .optimise import OptimiserStatus
from .options import CalibrationOptions
from .uncertainty import GAUSS_NEWTON_COVERAGE, Uncertainty

__all__ = [
    "SCHEMA_VERSION",
    "Calibration",
    "calibration_caveats",
    "no_interval_said",
    "phantom_frame",
    "reference_state_said",
]

FRAMES = {
    "fiducial": "scans mapped by the fiducial registration only (no ICP)",
    "icp": "after rigid ICP of the measured onto the simulated surface "
    "(biased low: it absorbs part of the model error)",
}


# A scan whose gravity lies within 10 degrees of the plate's normal (a prone or supine
# posture) leaves the in-plane axes to the registration's gravity error (about a degree,
# README): it does not define them.
_MIN_IN_PLANE = float(np.sin(np.radians(10.0)))


def calibration_caveats(record: dict) -> list[str]:
    """What a reader of figures made from this calibration must be told, one line each.

    A model misfit (the interval is an effective c1's), an optimiser that did not converge
    or ended on a bound, a retry mesh (its discretisation error may outrun the mesh
    check's bound), a repaired reference surface (its back clamped within size/5), a
    model mesh few elements tall for the body, a mesh check that failed on every check
    mesh (the interval is the noise's alone), and a surface interval that is not the
    series one.

    Parameters
    ----------
    record : dict
        ``calibration.json``.
    """
    said = []
    if (record.get("model_fit") or {}).get("verdict") == "misfit":
        said.append(
            "model misfit (calibration.json model_fit): c1 is an effective c1, and its "
            "interval and every band from it cover noise and mesh, not this model error"
        )
    opt = record.get("optimiser") or {}
    if opt and not opt.get("success", True):
        said.append(f"the optimiser did not converge ({opt.get('message')})")
    if opt.get("bound"):
        side = f"the {opt['bound']}" if opt["bound"] in ("lower", "upper") else "a"
        said.append(f"c1 ended on {side} bound of its search range")
    mesh = record.get("mesh") or {}
    if mesh.get("failed_sizes"):  # review AO: a retry mesh's error outran its bound
        tried = ", ".join(f"{f['mesh_size_mm']:g}" for f in mesh["failed_sizes"])
        said.append(
            f"calibrated on the {mesh.get('size_mm', 0):g} mm retry mesh (no FE solution on "
            f"{tried} mm): a coarser mesh's discretisation error can exceed the mesh "
            "check's bound, so the interval may miss c1 (README, the independent "
            "generator's benchmark); a finer --mesh-size may solve where the default did not"
        )
    support = mesh.get("support") or {}
    if support.get("surface") == "repaired":  # review BN: a log line and a key said it
        said.append(
            f"the reference surface was meshed after TetGen's repair (its decimated and "
            f"remeshed forms rejected), its back clamped within "
            f"{support.get('back_tol_mm', 0):.2g} mm of the plate (size/5): the rim's wall "
            "that low is clamped too, which stiffens the model (size/5 on a remeshed "
            "surface of an independent generator's scan: c1 2.2 % low, its interval missing "
            "the truth; model.reference.remesh_tolerance_mm); check "
            "calibration/reference_mesh.vtu, or try another --mesh-size"
        )
    k = mesh.get("elements_in_height")
    if k is not None and k < MIN_ELEMENTS_IN_HEIGHT:  # review BN: said in the log only
        said.append(
            f"the model mesh has {k:.1f} elements of {mesh.get('size_mm', 0):g} mm through "
            f"the body's {mesh.get('height_mm', 0):.0f} mm height, fewer than "
            f"{MIN_ELEMENTS_IN_HEIGHT:g} (the twins': about 6): its discretisation error "
            "may exceed the mesh check's bound, on meshes as coarse; a --mesh-size of about "
            f"{mesh.get('height_mm', 0) / 6:.0f} mm meshes it as the twins are"
        )
    unc = record.get("uncertainty") or {}
    check = unc.get("mesh_check")
    if check and check.get("gci_ln_c1") is None and unc.get("c1_ci95_pa") is not None:
        # review BN: the interval then covers the noise alone, 5-10 times narrower than
        # with a discretisation bound (README, the independent generator: 411.9-415.1 Pa
        # around a truth of 420 where the bound was 4.5 %), and nothing said so
        said.append(
            "no mesh check solved (calibration.json uncertainty.mesh_check): the c1 "
            "interval covers the residuals' noise only, not the mesh's discretisation "
            "error, and may miss c1; a finer --mesh-size may solve where the check did not"
        )
    if record.get("objective") == "surface" and unc.get("method") == "gauss-newton":
        said.append(
            "the c1 interval is the Gauss-Newton one, not the series one: "
            f"{GAUSS_NEWTON_COVERAGE} (README, the interval's coverage)"
        )
    return said


def no_interval_said(interval: dict | None) -> str:
    """Why a calibration has no 95 % interval, from ``uncertainty.interval``'s ``open``.

    The nipple profile says which side is open and why (a failed FE solve or the search
    limit); other intervals are open only where the data do not bound c1.
    """
    why = [w for w in (interval or {}).get("open") or [] if w]
    return "no 95 % interval: " + ("; ".join(why) if why else "the data do not bound c1")


def reference_state_said(reference_state: str, recovery: dict | None) -> str:
    """``reference state X``, with the elements an ``unload`` calibration solved.

    Parameters
    ----------
    reference_state : str
        ``calibration.json``'s ``reference_state``.
    recovery : dict or None
        Its ``reference_recovery`` (``method``: ``spatial`` where the stress-free
        elements were curved).

    Returns
    -------
    str
    """
    curved = reference_state == "unload" and (recovery or {}).get("method") == "spatial"
    return f"reference state {reference_state}" + (
        " (curved stress-free elements)" if curved else ""
    )


def phantom_frame(reference, others: Iterable = ()) -> np.ndarray:
    """Rotation ``R_ref_from_phantom`` (3, 3) of the phantom frame of posture angles.

    The phantom frame's columns in the reference scan's frame: ``z`` points from the back
    plate into the breast (minus the back plate's outward normal). A posture angle ``a``
    is the gravity ``R_ref_from_phantom @ (cos a, 0, sin a)`` in the transverse plane,
    ``@ (0, cos a, sin a)`` in the sagittal one (:func:`fem.postures.gravity_for_angle`;
    0 degrees left lateral). So the part of a scan's gravity orthogonal to ``z`` is
    ``cos a`` times ``x`` (sagittal: ``y``): that axis is the part normalised, its sign
    that of ``cos a`` of the scan's nominal angle (``posture.angle_deg``; none given: 0,
    a reference at 180 degrees gives the same frame as one at 0). The reference scan
    defines it; where its gravity lies within 10 degrees of the plate's normal, the first
    of ``others`` whose gravity does not. Then ``y = z x x`` (sagittal: ``x = y x z``).

    Parameters
    ----------
    reference : ScanMeasurement
        The reference scan (its gravity, back plane and nominal posture, reference frame).
    others : iterable of ScanMeasurement
        The session's other scans, tried in turn where the reference's gravity is normal
        to its plate.

    Returns
    -------
    ndarray, shape (3, 3)

    Raises
    ------
    ValueError
        No scan's gravity has a part in the plate's plane.
    """
    z = -np.asarray(reference.back_normal, float)
    z /= np.linalg.norm(z)
    for scan in [reference, *others]:
        g = np.asarray(scan.gravity_ref, float)
        axis = g - (g @ z) * z
        if np.linalg.norm(axis) < _MIN_IN_PLANE:
            continue
        angle = scan.posture_angle_deg or 0.0
        axis *= (-1.0 if np.cos(np.radians(angle)) < 0 else 1.0) / np.linalg.norm(axis)
        if scan.posture_plane == "sagittal":
            return np.column_stack([np.cross(axis, z), axis, z])
        return np.column_stack([axis, np.cross(z, axis), z])
    raise ValueError(
        f"the gravity of the reference scan {reference.name!r} (and of every other scan) "
        "lies within 10 degrees of the back plate's normal: the posture angles' axes are "
        "undefined; add a scan in a lateral posture"
    )


@dataclass(frozen=True)
class Calibration:
    """A fitted c1 with its uncertainty, the optimiser's record and the fitted model.

    Attributes
    ----------
    c1_pa : float
        Calibrated neo-Hookean c1 (shear modulus 2 c1), Pa.
    c1_ci95_pa : tuple of float or None
        95 % interval (noise and mesh check; the likelihood profile for ``nipple``);
        None when the data do not bound c1 within x/÷ 4.
    objective : str
    objective_value_mm2 : float
        ``J = mean(r^2) / 2`` at ``c1_pa``.
    reference_state : str
    uncertainty : Uncertainty
    model_fit : dict or None
        The misfit test of the surface residual at the fit
        (:meth:`calib.stats.ModelFit.as_json`: ``verdict`` ``fits`` or ``misfit``,
        ``p_value``, the noise model); None for the nipple and landmarks objectives.
    mesh_check : MeshCheck or None
    optimiser : OptimiserStatus
    history : tuple of dict
        Every objective evaluation (``c1_pa``, ``objective``, ``gradient``, ``rms_mm``,
        ``wall_s``; ``failed`` for a failed FE solve).
    profile : tuple of dict
        The likelihood profile's rows.
    mesh : dict
        ``n_tets``, ``n_nodes``, ``size_mm``, ``failed_sizes``, ``formulation``.
    reference_recovery : dict
        ``method`` and ``inverted_elements`` of the stress-free recovery.
    fe_solves : int
    wall_s : float
    options : CalibrationOptions
    density_kg_m3 : float
    calibrator : Calibrator
        The live model at the calibrated c1 (mesh, stress-free geometry, warm starts),
        used by :func:`calib.evaluate`; not part of the JSON form.
    """

    c1_pa: float
    c1_ci95_pa: tuple[float, float] | None
    objective: str
    objective_value_mm2: float
    reference_state: str
    uncertainty: Uncertainty
    model_fit: dict | None
    mesh_check: MeshCheck | None
    optimiser: OptimiserStatus
    history: tuple[dict, ...]
    profile: tuple[dict, ...]
    mesh: dict
    reference_recovery: dict
    fe_solves: int
    wall_s: float
    options: CalibrationOptions
    density_kg_m3: float
    calibrator: object = field(repr=False, compare=False, default=None)

    @property
    def theta(self) -> float:
        """``ln c1`` (c1 in Pa), the fitted parameter."""
        return float(np.log(self.c1_pa))

    def model_json(self) -> dict:
        """The fitted model's physical description (the ``model`` block)."""
        cal = self.calibrator
        o = self.options
        doc = {
            "law": "neo-hookean (uncoupled), W = c1 (I1bar - 3) + U(J)",
            "nu": o.nu,
            "density_kg_m3": self.density_kg_m3,
            "formulation": o.formulation,
            "support": "clamped",
            "g_m_s2": None,
            "reference_scan": None,
            "reference_posture": None,
            "tumour_stress_free_mm": None,
            "nipple_node": None,
            "nipple_node_offset_mm": None,
            "R_ref_from_phantom": None,
        }
        if cal is not None:
            fm = cal.fm
            doc["g_m_s2"] = fm.g_m_s2
            doc["reference_scan"] = cal.measurements.reference.name
            doc["reference_posture"] = cal.measurements.reference.nominal_posture
            doc["nipple_node"] = k = int(cal.mesh.node_set("nipple")[0])
            off = cal.mesh.nodes_mm[k] - cal.measurements.reference.nipple_mm
            doc["nipple_node_offset_mm"] = float(np.linalg.norm(off))
            ms = cal.measurements
            doc["R_ref_from_phantom"] = phantom_frame(ms.reference, ms.scans.values()).tolist()
            if cal.tumour is not None and fm.stress_free_nodes_mm is not None:
                doc["tumour_stress_free_mm"] = cal.tumour.place_mm(fm.stress_free_nodes_mm).tolist()
        return doc

    def to_json(self, *, scans: dict | None = None, provenance: dict | None = None) -> dict:
        """The ``calibration.json`` document (see the README's output contract).

        Parameters
        ----------
        scans : dict, optional
            Per-scan results (``ScanEvaluation.to_json()`` of :func:`calib.evaluate`).
        provenance : dict, optional
            Versions, input hashes and options (:func:`calib.io.provenance`).
        """
        ci = self.c1_ci95_pa
        return {
            "schema_version": SCHEMA_VERSION,
            "c1_pa": self.c1_pa,
            "c1_ci95_pa": list(ci) if ci is not None else None,
            "objective": self.objective,
            "objective_value_mm2": self.objective_value_mm2,
            "reference_state": self.reference_state,
            "uncertainty": asdict(self.uncertainty)
            | {"mesh_check": asdict(self.mesh_check) if self.mesh_check else None},
            "model_fit": self.model_fit,
            "frames": FRAMES,
            "scans": scans or {},
            "iterations": self.optimiser.iterations,
            "fe_solves": self.fe_solves,
            "optimiser": self.optimiser.to_json(),
            "reference_recovery": self.reference_recovery,
            "history": list(self.history),
            "profile": list(self.profile),
            "mesh": self.mesh,
            "model": self.model_json(),
            "wall_s": self.wall_s,
            "provenance": provenance or {},
        }

    def summary(self) -> str:
        """One line: c1, interval, objective, reference state."""
        ci = self.c1_ci95_pa
        interval = (
            f"95 % interval {ci[0]:.1f} - {ci[1]:.1f} Pa"
            if ci is not None
            else no_interval_said(self.uncertainty.interval)
        )
        state = reference_state_said(self.reference_state, self.reference_recovery)
        return f"c1 = {self.c1_pa:.1f} Pa ({interval}), objective {self.objective}, {state}"

    def __repr__(self) -> str:
        return (
            f"Calibration({self.summary()}; {self.optimiser.iterations} iterations, "
            f"{self.fe_solves} FE solves, {self.wall_s:.0f} s)"
        )

    def _repr_html_(self) -> str:
        from html import escape

        ci = self.c1_ci95_pa
        rows = [
            ("c1", f"{self.c1_pa:.1f} Pa"),
            ("95 % interval", f"{ci[0]:.1f} – {ci[1]:.1f} Pa" if ci else "not bounded"),
            ("objective", f"{self.objective} ({self.objective_value_mm2:.4g} mm²)"),
            ("reference state", self.reference_state),
            (
                "optimiser",
                f"{'converged' if self.optimiser.success else 'NOT converged'}: "
                f"{self.optimiser.message}",
            ),
            ("iterations / FE solves", f"{self.optimiser.iterations} / {self.fe_solves}"),
            ("model mesh", f"{self.mesh.get('n_tets')} tets, {self.mesh.get('size_mm')} mm"),
            ("wall time", f"{self.wall_s:.0f} s"),
        ]
        body = "".join(
            f"<tr><th style='text-align:left'>{escape(k)}</th><td>{escape(v)}</td></tr>"
            for k, v in rows
        )
        return f"<table><caption>Calibration</caption>{body}</table>"
