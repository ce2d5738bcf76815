"""The calibration objective: the model, the measurements and ``J(ln c1)`` with its gradient.

The parameter is ``theta = ln c1``; ``J = mean(r^2) / 2`` of the chosen objective's
residuals over the calibration scans, with the analytic gradient of
:mod:`calib.model.forward`. The optimiser is in :mod:`calib.fitting.optimise`.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

import fem
from fem.probe import MaterialPoint
from fem.units import DEFAULT_DENSITY_KG_M3

from ..data.measurements import Measurements, ScanMeasurement
from ..data.session import SessionError
from ..model.forward import ForwardModel, ReferenceRecoveryFailed
from ..model.reference import reference_mesh_with_support
from ..model.residuals import Residuals, SimulatedSurface, scan_residuals
from .options import CalibrationOptions

__all__ = ["Calibrator", "EvaluationFailed"]


class EvaluationFailed(fem.ConvergenceError):
    """The objective could not be evaluated at a c1 (its FE solve failed).

    Attributes
    ----------
    stage : {"stress-free reference", "posture"} or None
        What failed (None where not said): the stress-free reference's recovery
        (:class:`calib.model.forward.ReferenceRecoveryFailed`) or a posture's solve.
    """

    # (a default, so that a process pool's worker can pickle it: the attribute travels
    # in the exception's __dict__)
    def __init__(
        self, message: str, *, stage: Literal["stress-free reference", "posture"] | None = None
    ):
        super().__init__(message)
        self.stage = stage


log = logging.getLogger(__name__)
#: A calibration scan's measured nipple displacement (mm) below which the first estimate
#: does not use it: a few times the nipple's measured noise (0.1-0.2 mm on the twins).
MIN_NIPPLE_DISPLACEMENT_MM = 0.5
#: ... or below this many times the scan's expected registration error at the nipple
#: (``tre_nipple_mm``), where that is more: with a 1 mm TRE a 0.6 mm "displacement" is
#: mostly error (review BN, N5). The twins' TREs are 0.03-0.04 mm.
NIPPLE_TRE_FACTOR = 3.0


def nipple_threshold_mm(scan) -> float:
    """The measured nipple displacement (mm) a scan needs for the first estimate to use it.

    :data:`MIN_NIPPLE_DISPLACEMENT_MM`, or :data:`NIPPLE_TRE_FACTOR` times the scan's
    ``tre_nipple_mm`` where that is more.

    Parameters
    ----------
    scan : ScanMeasurement

    Returns
    -------
    float
    """
    try:
        tre = float(getattr(scan, "tre_nipple_mm", None))
    except (TypeError, ValueError):  # not recorded (or not a number): the floor alone
        tre = 0.0
    tre = tre if np.isfinite(tre) else 0.0
    return max(MIN_NIPPLE_DISPLACEMENT_MM, NIPPLE_TRE_FACTOR * tre)


@dataclass
class Calibrator:
    """Holds the model, the measurements and the history of one calibration."""

    measurements: Measurements
    options: CalibrationOptions
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3
    history: list = field(default_factory=list)

    def __post_init__(self) -> None:
        o = self.options
        self.calibration_scans = self.measurements.with_role("calibration")
        if not self.calibration_scans:
            raise SessionError("the session has no scan with role 'calibration'")
        ref = self.measurements.reference
        self.mesh, self.support = reference_mesh_with_support(
            ref, size_mm=o.mesh_size_mm, max_dihedral_deg=o.mesh_max_dihedral_deg
        )
        # a failed recovery is a failed evaluation, except that a mesh admitting no
        # straight stress-free elements is solved with curved ones (and says so)
        self.fm = self._forward_model(spatial_fallback=o.reference_state == "unload")
        self.sim = SimulatedSurface.of(self.mesh)
        self.points = {s.name: s.surface_points(max_points=o.max_points, seed=o.seed)
                       for s in self.measurements.scans.values()}  # fmt: skip
        # the tumour: a material point of the reference scan, followed through the solves
        self.tumour = None if ref.tumour_mm is None else self._tumour(ref.tumour_mm)
        self.states: dict = {}
        self._cache = None
        self.gauss_newton_curvature = 1.0
        #: True once :meth:`first_estimate` fell back to the guess (no nipple moved enough)
        self.first_estimate_from_guess = False

    def _forward_model(self, *, spatial_fallback: bool) -> ForwardModel:
        """The homogeneous clamped model of :attr:`mesh` with the options' material."""
        o = self.options
        return ForwardModel(
            self.mesh, self.measurements.reference.gravity_ref, nu=o.nu,
            density_kg_m3=self.density_kg_m3, reference_state=o.reference_state,
            formulation=o.formulation, fixed_point_fallback=False,
            spatial_fallback=spatial_fallback,
        )  # fmt: skip

    def curved(self) -> Calibrator:
        """A new calibrator of this mesh and these points on curved stress-free elements.

        Its model recovers the reference with curved elements (the prestressed loaded
        mesh, ``unload_method="spatial"``) at every c1, with no fallback; its history is
        empty, and this calibrator, its recoveries and its history are left as they are
        (:func:`calib.fitting.pipeline.fit` keeps them where the curved fit fails).

        Returns
        -------
        Calibrator
        """
        new = copy.copy(self)
        new.history = []
        new.fm = self._forward_model(spatial_fallback=False)
        new.fm.use_spatial()
        new.states, new._cache, new.gauss_newton_curvature = {}, None, 1.0
        return new

    def _tumour(self, tumour_mm: np.ndarray) -> MaterialPoint:
        """The tumour's material point; one outside the model mesh at the nearest inside."""
        disc = self.fm.discretization
        point = MaterialPoint.locate(disc, tumour_mm, outside="nearest")
        off = float(np.linalg.norm(point.place_mm(disc.mesh.nodes_mm) - tumour_mm))
        if off > 1e-3:
            msg = "the tumour centre %s lies %.2f mm outside the model mesh (its surface cuts "
            log.warning(
                msg + "the scan's curved one): followed from the nearest point inside",
                np.round(tumour_mm, 2),
                off,
            )
        return point

    def targets(self) -> list[ScanMeasurement]:
        """Every scan but the reference."""
        return [s for s in self.measurements.scans.values() if s.role != "reference"]

    def residuals(
        self, theta: float, scans, *, gradient: bool, retry: bool = True
    ) -> dict[str, Residuals]:
        """Solve the postures at theta and compute each scan's residuals."""
        gravities = {s.name: s.gravity_ref for s in scans}
        states = self.fm.evaluate(theta, gravities, gradient=gradient, retry=retry)
        self.states = states
        out = {}
        for s in scans:
            st = states[s.name]
            tumour = self.tumour_position(st, gradient)
            out[s.name] = scan_residuals(
                self.options.objective, s, self.mesh, self.sim, st.positions_mm,
                st.dpositions_mm if gradient else None, surface_points_mm=self.points[s.name],
                tumour=tumour,
            )  # fmt: skip
        return out

    def tumour_position(self, st, gradient: bool):
        """``(p, dp)`` of the simulated tumour centre (mm; dp per unit ln c1), or None."""
        if self.tumour is None:
            return None
        p = self.tumour.position_mm(self.fm.state_nodes_mm, st.state)
        dp = self.tumour.position_mm(self.fm.current_dX, st.dstate) if gradient else None
        return p, dp

    def objective(self, theta_arr: np.ndarray) -> tuple[float, np.ndarray]:
        """``J(theta)`` and its gradient in ``theta = ln c1``.

        Raises
        ------
        EvaluationFailed
            The FE solve (or the stress-free recovery) failed at this theta; the failure
            is recorded in :attr:`history` with its ``stage``. The optimiser backtracks
            from it.
        """
        theta = float(theta_arr[0])
        if self._cache is not None and self._cache[0] == theta:
            return self._cache[1]
        t0 = time.perf_counter()
        try:
            res = self.residuals(theta, self.calibration_scans, gradient=True)
        except fem.ConvergenceError as exc:
            log.warning("FE failed at c1=%.1f Pa (%s)", np.exp(theta), exc)
            stage = (
                "stress-free reference" if isinstance(exc, ReferenceRecoveryFailed) else "posture"
            )
            self.history.append({"c1_pa": float(np.exp(theta)), "objective": None,
                                 "failed": True, "stage": stage, "reason": str(exc)})  # fmt: skip
            raise EvaluationFailed(
                f"no FE solution at c1 = {np.exp(theta):.1f} Pa: {exc}", stage=stage
            ) from exc
        r = np.concatenate([v.r for v in res.values()])
        dr = np.concatenate([v.dr for v in res.values()])
        J, g = 0.5 * float(np.mean(r**2)), float(np.mean(r * dr))
        self.gauss_newton_curvature = float(np.mean(dr**2))
        self.history.append({"c1_pa": float(np.exp(theta)), "objective": J, "gradient": g,
                             "rms_mm": float(np.sqrt(np.mean(r**2))),
                             "wall_s": time.perf_counter() - t0})  # fmt: skip
        log.info("c1 = %8.2f Pa  J = %.5g mm^2  dJ/dln c1 = %.4g", np.exp(theta), J, g)
        self._cache = (theta, (J, np.array([g])))
        return J, np.array([g])

    def first_estimate(self, *, load_fraction: float = 0.05) -> float:
        """c1 from the linear response at the guess: displacement ~ g / c1 (nipple landmarks).

        One shortcut solve (no reference recovery) under ``load_fraction`` of the posture
        change, where the response is nearly linear and Newton converges in a step or two;
        its nipple displacement, scaled up, against the measured one. A full-load solve at
        a poor guess is the hardest problem of the calibration (a 2 g flip of a soft
        phantom), which is why it is avoided here. On the quick twin this estimate is
        within about 10 % of the calibrated c1 (470 vs 424 Pa).
        """
        theta = np.log(self.options.c1_guess_pa)
        fm = ForwardModel(self.mesh, self.fm.gravity_ref, nu=self.fm.nu,
                          density_kg_m3=self.fm.density_kg_m3, reference_state="shortcut",
                          formulation=self.fm.formulation,
                          g_m_s2=self.fm.g_m_s2 * load_fraction)  # fmt: skip
        states = fm.evaluate(theta, {s.name: s.gravity_ref for s in self.calibration_scans},
                             gradient=False)  # fmt: skip
        self.fm.solves += fm.solves
        nipple = int(self.mesh.node_set("nipple")[0])
        x_ref = self.mesh.nodes_mm[nipple]
        ref_n = self.measurements.reference.nipple_mm
        ratios = []
        for s in self.calibration_scans:
            d_sim = np.linalg.norm(states[s.name].positions_mm[nipple] - x_ref) / load_fraction
            d_meas = np.linalg.norm(s.nipple_mm - ref_n)
            if d_meas > nipple_threshold_mm(s):
                ratios.append(d_sim / d_meas)
        est = self.options.c1_guess_pa * (float(np.median(ratios)) if ratios else 1.0)
        if not 20.0 <= est <= 1e5:
            listed = ", ".join(f"{r:.3g}" for r in ratios)
            why = (
                f"the guess {self.options.c1_guess_pa:.3g} Pa times the median of the "
                f"nipple's simulated over measured displacements ({listed})"
                if ratios
                else f"the guess (--c1-guess {self.options.c1_guess_pa:.3g})"
            )
            log.warning(
                "the first estimate c1 = %.3g Pa (%s) lies outside 20 Pa-100 kPa: clipped to "
                "that range",
                est,
                why,
            )
        est = float(np.clip(est, 20.0, 1e5))
        self.first_estimate_from_guess = not ratios
        if not ratios:
            log.warning(
                "the nipple moved less than %.1f mm (or %g times the scan's expected "
                "registration error there, where that is more) in every calibration scan: "
                "the first estimate is the guess (--c1-guess), c1 = %.0f Pa, and the "
                "search spans x/÷ 4 around it",
                MIN_NIPPLE_DISPLACEMENT_MM,
                NIPPLE_TRE_FACTOR,
                est,
            )
        return est
