"""``diagnose``: find where model and scans disagree, name the missing effect, refit, verdict.

Steps (the issue's; no files are written here, see :mod:`calib.workflows.diagnose`):

1. *Null fit.* ``ln c1`` refitted alone to the diagnosis scans (every scan but the
   reference and the held-out one), from the calibration's c1: the score tests need the
   residual at the fit of what they condition on.
2. *Noise model* (:func:`calib.stats.estimate_noise`, short range, from the residual's
   own variogram; the session's: the least-disturbed scan's fit,
   :func:`calib.stats.noise.session_noise`) and the *misfit test*
   (:func:`calib.stats.misfit_test`). With ``noise_profile="plate"`` the null fit's
   residual first gives its spread by height above the back plate
   (:func:`calib.stats.height_profile`); every residual and field is divided by it
   (:attr:`calib.discrepancy.problem.Problem.profile`, weighted least squares) and the
   null fit is repeated, so the stationary noise model sees a spread that does not
   depend on height.
3. *Localise:* a significance map and a region summary per scan
   (:mod:`calib.discrepancy.localise`).
4. *Screen:* each requested effect's sensitivity field (:mod:`calib.discrepancy.fields`)
   with what ``ln c1`` and the per-scan offsets absorb projected out, a score test, Holm
   across effects (a nuisance's per-scan columns tested jointly as one effect);
   identifiability and confounding (:mod:`calib.discrepancy.screen`). With
   ``mesh_error="absorbed"`` the model mesh's own discretisation error joins what is
   projected out: the null fit's c1 solved on a mesh
   :data:`calib.discrepancy.fields.COARSER_FACTOR` times coarser gives its shape
   (:func:`calib.discrepancy.fields.discretisation_field`).
5. *Confirm and name* by forward selection with backward pruning: the significant
   physical effects, strongest first (``max_candidates`` per round), are refitted jointly
   with ``ln c1`` by the full nonlinear FE model (:mod:`calib.discrepancy.refit`); the
   significant nuisances only when none of them passes (:func:`_candidates`). An effect
   is named only if (a) its score test is significant after Holm at the current model,
   (b) the leave-one-posture-out prediction improves, (c) its fitted parameters are
   inside their physical range and not on a bound, and (d) it explains at least
   ``min_explained`` of the residual above the noise floor: ``(MS_before - MS_after) /
   (MS_before - floor) >= 0.5``, mean squares over the diagnosis scans less each scan's
   offset, ``floor`` the lowest short-range noise variance any model tried leaves (the
   session's noise, 20 mm variogram: the residual of a correct model is noise; a wrong
   one keeps the misfit in its variogram). The share is taken on the points farther
   than ``explained_margin_mm`` from the back plate (default one model element) and on
   every diagnosed point: the first layer of elements at the clamped edge carries the
   model's own discretisation error, which no library effect explains
   (:func:`_judged_points`), and a physical effect passes on either set of points (a
   sliding plate acts at the plate), a nuisance on both. Candidates passing
   with near-equal evidence (explained fractions within ``near_equal``) and similar
   projected signatures (``|cos| >= confounded_above``) are named together as
   confounded. After a second effect is added, each named one must stay significant at
   the model without it (backward pruning).
6. *Verdict* (exact strings): ``no missing effect``; ``named: X``;
   ``named: X | Y (confounded)``; ``named: X (+ unexplained remainder)``;
   ``unexplained``; ``not identifiable from these data: Z`` (two effects named apart:
   ``named: X + Y``).
7. *The gap:* the final model on every scan, the held-out one included (it was never
   fitted), against c1 alone on the same mesh: the calibration's saved states, or the
   null fit where the diagnosis runs on another mesh (the calibration's own errors are
   then kept beside).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Literal, get_args

import numpy as np

import fem

from ..choices import MeshErrorTreatment, NoiseProfile
from ..data.work import WorkFolder, as_work_folder, ingest_record
from ..evaluation import ScanMetrics, scan_metrics
from ..fitting.meshcheck import gci_at_size
from ..fitting.options import MESH_SIZE_RANGE_MM
from ..model.effects import ADMISSIBLE, LIBRARY, SKIN_THICKNESS_MM
from ..stats import NoiseFit, NoiseModel, height_profile, parameter_intervals
from ..stats.noise import MAX_LAG_MM
from ..stats.scores import MISFIT_ALPHA, SCREEN_ALPHA
from .fields import COARSER_FACTOR, FieldSet, discretisation_column, discretisation_field
from .limits import parameter_limits
from .localise import TUMOUR_MM, region_labels, region_radii_mm, significance_map
from .problem import (
    RIM_MARGIN_MM,
    DiagnosisError,
    Problem,
    build_problem,
    failed_scans,
    inclusions_left_out,
    plate_height_mm,
    rim_margin_of,
)
from .refit import PHYSICAL, SLIDING_PROBE_MULTIPLES, Refit, lopo, refit
from .screen import (
    Screen,
    mesh_error_check,
    offset_columns,
    sample_of,
    screen,
    session_noise,
)

__all__ = ["DEFAULT_EFFECTS", "Candidate", "Diagnosis", "DiagnosisOptions", "diagnose"]

log = logging.getLogger(__name__)

#: Screened by default: the whole library.
DEFAULT_EFFECTS = (
    "skin", "sliding", "inclusions", "mooney", "poisson", "density", "gravity", "registration",
)  # fmt: skip
#: The noise model's short range (mm): the tests' variogram reaches to NOISE_LAG_MM, the
#: noise floor's to FLOOR_LAG_MM, both for the twins' 75 mm tall body and scaled with the
#: body's height like the regions (:attr:`Problem.region_scale`: 1 for every twin).
#: Review W's dome half as tall (8 draws, a smooth misfit over 3 mm correlated noise): the
#: fitted length 5.4 mm with 40 mm lags (a misfit absorbed), 3.0 with 20; the misfit test
#: caught the misfit in 3 and 4 of 8 (the smaller body holds fewer independent samples).
NOISE_LAG_MM = MAX_LAG_MM
FLOOR_LAG_MM = 20.0
#: ``DiagnosisOptions.noise_profile``'s choices (``diagnose --noise-profile``).
NOISE_PROFILES = get_args(NoiseProfile)
#: ``DiagnosisOptions.mesh_error``'s choices (``diagnose --mesh-error``).
MESH_ERRORS = get_args(MeshErrorTreatment)
MAP_KERNEL_MM = 10.0  # the significance map's smoothing (a pad's print, a rim band), scaled


#: The numeric options and the command's flag of each (None: no flag), for messages
_NUMBER_FLAGS = {
    "alpha": "--alpha",
    "min_explained": None,
    "skin_thickness_mm": "--skin-thickness",
    "mesh_size_mm": "--mesh-size",
    "inclusion_mesh_mm": "--inclusion-mesh",
    "rim_margin_mm": "--rim-margin",
    "explained_margin_mm": "--explained-margin",
}


@dataclass(frozen=True)
class DiagnosisOptions:
    """Options of ``phantom-calib diagnose``.

    Attributes
    ----------
    effects : tuple of str
        Library effects to screen (:data:`calib.model.effects.LIBRARY`). ``sliding`` is
        screened by a stiff-spring probe and refitted as ``ln k`` of the plate's springs.
    holdout : str or None
        Scan never fitted (default: the first validation scan; ``"none"``: none).
    alpha : float
        Family-wise error rate of the screening (Holm).
    misfit_alpha : float
        Level of the misfit test (see :func:`calib.discrepancy.screen.screen`).
    skin_thickness_mm : float
        Thickness of the skin effect's band (mm; in (0, 10]). The surface sees about
        ``(ratio - 1) * thickness`` of a thin layer, so the fitted ratio stands for that
        product at this thickness; the refit's intervals give it (``excess_mm``).
    max_points : int or None
        Measured points per scan (default: the calibration's).
    rim_margin_mm : float or "element"
        Points nearer the back plate (mm) are not diagnosed, only mapped; ``"element"``:
        one model element (:func:`calib.discrepancy.problem.rim_margin_of`); 0 keeps them.
    mesh_size_mm : float or None
        Diagnose on a model mesh of this size, built from the reference scan, instead of
        the calibration's (None). A finer mesh tells discretisation error from a missing
        effect (every FE solve costs more: about (h / size)^3).
    inclusion_mesh_mm : float or None
        Diagnose on a model mesh built from the reference scan (of ``mesh_size_mm``, else
        the calibration's size) whose segmented inclusions are meshed as spheres with
        elements of this size (mm) inside, instead of the calibration's mesh (None): a
        stiff inclusion's print is local, and on the calibration's mesh the inclusions
        only stiffen the elements they cut (:func:`calib.model.effects.inclusion_mix`).
        Without ``mesh_size_mm``, where the calibration's size admits no straight
        stress-free reference, the next size is taken
        (:func:`calib.discrepancy.problem.next_mesh_sizes`) and the mesh note says so.
    noise_profile : {"flat", "plate"}
        ``"flat"``: one noise level at every height (the default). ``"plate"``: the
        noise level by height above the back plate, measured on the null fit's residual
        (:func:`calib.stats.height_profile`); residuals and fields are weighted by it.
    mesh_error : {"ignored", "absorbed"}
        ``"ignored"`` (the default): the tests condition on ``ln c1``, the per-scan
        offsets and the named effects. ``"absorbed"``: the score tests, the misfit test
        and the parameter limits also condition on one direction of the model mesh's own
        discretisation error, the residual change from the model mesh to one
        :data:`calib.discrepancy.fields.COARSER_FACTOR` times coarser at the null fit's c1
        (:mod:`calib.discrepancy.fields`; one more mesh, two stress-free recoveries and
        one FE solve per diagnosis scan). The refits, their intervals, the share
        explained, leave-one-posture-out, the noise model, the maps and the gap do not.
        Where that mesh cannot be built or solved the diagnosis goes on without it and
        says so (``model_mesh.error`` in ``diagnosis.json``).
    max_candidates : int
        Significant effects refitted by FE per forward-selection round (physical effects
        first; nuisances only when no physical candidate passes).
    max_named : int
    min_explained : float
        Share of the residual above the noise floor a named effect must explain.
    explained_margin_mm : float or "element"
        That share is measured on the points farther than this from the back plate (mm;
        ``"element"``, the default: one model element,
        :func:`calib.discrepancy.problem.rim_margin_of`; at most the
        ``rim_margin_mm`` band: every diagnosed point), against the noise floor of those
        points. The tests still use every diagnosed point. A physical effect passes on
        either set of points (a sliding plate acts at the plate itself); a nuisance (a
        per-scan gravity angle or rigid offset, the explanation of last resort) must
        explain that share on both. The clamped edge is a stress
        singularity: on null twins a c1-only fit leaves 0.10-0.61 mm rms within 16 mm of
        the plate against 0.06-0.14 mm beyond 30 mm
        (:func:`calib.discrepancy.problem.rim_margin_of`), a discretisation error no
        library effect explains; counted as residual to explain, it kept a correctly
        refitted effect (stiff inclusions, c1 back on the truth, a better
        leave-one-posture-out prediction) at 23 % of it (59 % beyond the element; the
        quick inclusions twin, seed 2).
    confounded_above : float
        ``|cos|`` of projected signatures from which two effects are confounded.
    near_equal : float
        Explained fractions within this ratio count as near-equal evidence.
    refit_iterations : int
    parameter_limits : bool
        For each physical effect the final screen did not find, also the size of its
        own parameter whose print that screen would estimate at the detectable size, by
        the full FE model at the final model (the null fit, or the refit with the named
        effects; :mod:`calib.discrepancy.limits`; a few FE solves of every
        diagnosis scan per effect, 30-250 s more on the quick twins). Off by default.
    """

    effects: tuple[str, ...] = DEFAULT_EFFECTS
    holdout: str | None = None
    alpha: float = SCREEN_ALPHA
    misfit_alpha: float = MISFIT_ALPHA
    skin_thickness_mm: float = SKIN_THICKNESS_MM
    max_points: int | None = None
    rim_margin_mm: float | Literal["element"] = RIM_MARGIN_MM
    mesh_size_mm: float | None = None
    inclusion_mesh_mm: float | None = None
    noise_profile: NoiseProfile = "flat"
    mesh_error: MeshErrorTreatment = "ignored"
    max_candidates: int = 2
    max_named: int = 2
    min_explained: float = 0.5
    explained_margin_mm: float | Literal["element"] = "element"
    confounded_above: float = 0.9
    near_equal: float = 0.8
    refit_iterations: int = 10
    parameter_limits: bool = False

    def __post_init__(self) -> None:
        # one name, not its letters (review AU)
        effects = (self.effects,) if isinstance(self.effects, str) else tuple(self.effects)
        object.__setattr__(self, "effects", effects)
        for name, flag in _NUMBER_FLAGS.items():  # review AU: '0.05' gave a bare TypeError
            v = getattr(self, name, None)
            if v is None or v == "element":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                said = f"{name} ({flag})" if flag else name
                raise DiagnosisError(f"{said} must be a number, got {v!r}")
        unknown = sorted(set(self.effects) - set(LIBRARY))
        if unknown:
            raise DiagnosisError(
                f"effects (--effects): unknown effect(s) {', '.join(unknown)}; the library "
                f"has {', '.join(sorted(LIBRARY))}"
            )
        if not self.effects:
            raise DiagnosisError("no effect to screen")
        if len(set(self.effects)) != len(self.effects):
            raise DiagnosisError(f"effects (--effects) given twice: {', '.join(self.effects)}")
        if not 0.0 < self.alpha < 0.5:
            raise DiagnosisError(f"alpha (--alpha) must lie in (0, 0.5), got {self.alpha}")
        if not 0.0 < self.min_explained <= 1.0:
            raise DiagnosisError(f"min_explained must lie in (0, 1], got {self.min_explained}")
        for name in ("rim_margin_mm", "explained_margin_mm"):
            m = getattr(self, name)
            if m != "element" and (isinstance(m, str) or not 0.0 <= m < 50.0):
                raise DiagnosisError(
                    f"{name} ({_NUMBER_FLAGS[name]}) must lie in [0, 50) mm or be 'element', "
                    f"got {m!r}"
                )
        lo, hi = MESH_SIZE_RANGE_MM
        if self.mesh_size_mm is not None and not lo <= self.mesh_size_mm <= hi:
            raise DiagnosisError(
                f"mesh_size_mm (--mesh-size) must lie in [{lo:g}, {hi:g}] mm, "
                f"got {self.mesh_size_mm}"
            )
        h = self.inclusion_mesh_mm
        if h is not None and not (lo <= h <= hi and h <= (self.mesh_size_mm or hi)):
            raise DiagnosisError(
                f"inclusion_mesh_mm (--inclusion-mesh) must lie in [{lo:g}, {hi:g}] mm and "
                f"not above mesh_size_mm ({self.mesh_size_mm}), got {h}"
            )
        if self.noise_profile not in NOISE_PROFILES:
            raise DiagnosisError(
                f"noise_profile (--noise-profile) must be one of {NOISE_PROFILES}, "
                f"got {self.noise_profile!r}"
            )
        if self.mesh_error not in MESH_ERRORS:
            raise DiagnosisError(
                f"mesh_error (--mesh-error) must be one of {MESH_ERRORS}, got {self.mesh_error!r}"
            )
        if not 0.0 < self.skin_thickness_mm <= 10.0:
            raise DiagnosisError(
                f"skin_thickness_mm (--skin-thickness) must lie in (0, 10] mm, "
                f"got {self.skin_thickness_mm}"
            )
        if self.max_candidates < 1 or self.max_named < 1:
            raise DiagnosisError("max_candidates and max_named must be >= 1")


@dataclass(frozen=True)
class Candidate:
    """An effect refitted in a forward-selection round and the naming criteria.

    Attributes
    ----------
    effect : str
    round : int
    significant : bool
    p_holm : float
    statistic : float
    lopo_before_mm2, lopo_after_mm2 : float or None
    lopo_improves : bool
    parameters : dict of str to float
    at_bound : tuple of str
    plausible : bool
    explained : float
        Share of the residual above the noise floor the refit explains (criterion d): on
        the points beyond ``explained_margin_mm`` against their own floor, or on every
        diagnosed point (:attr:`explained_all_points`), the larger of the two for a
        physical effect and the smaller for a nuisance.
    passes : bool
    c1_pa : float
    rms_mm : float
    reason : str
        Why it was not named ("" when it passes).
    explained_all_points : float
        The same share on every diagnosed point (reported, not judged).
    """

    effect: str
    round: int
    significant: bool
    p_holm: float
    statistic: float
    lopo_before_mm2: float | None
    lopo_after_mm2: float | None
    lopo_improves: bool
    parameters: dict
    at_bound: tuple
    plausible: bool
    explained: float
    passes: bool
    c1_pa: float
    rms_mm: float
    reason: str
    explained_all_points: float = float("nan")

    def as_json(self) -> dict:
        """Plain JSON."""
        out = dict(vars(self))
        out["at_bound"] = list(self.at_bound)
        for k in ("p_holm", "statistic", "explained", "c1_pa", "rms_mm", "explained_all_points"):
            out[k] = _num(out[k])
        return out


def _screen_unit(effect: str, prob: Problem) -> str:
    """What one unit of the effect's screening column (its one-step estimate) is."""
    if effect == "sliding":
        return (
            f"probe amplitude, 1 = tangential springs of {prob.sliding_probe_pa_per_mm:g} "
            f"Pa/mm, sized by c1 and the body's {prob.body_height_mm:.1f} mm height"
        )
    if effect == "poisson":
        return "change of nu from the model's"
    return LIBRARY[effect].unit


def _num(v):
    return float(v) if v is not None and np.isfinite(v) else None


@dataclass(frozen=True)
class ScanGap:
    """A scan's errors before (c1 alone) and after (the final model), on one mesh.

    Attributes
    ----------
    name, role : str
        Role in the diagnosis: ``diagnosis`` (fitted) or ``holdout``.
    before, after : ScanMetrics
        c1 alone (the calibration, or the null fit when the diagnosis runs on another
        mesh) and the final model, both on the diagnosis mesh.
    residual_before_mm, residual_after_mm : ndarray
        Signed residuals of the diagnosis' points (offset included) to the curved model
        surface (:meth:`calib.model.residuals.SimulatedSurface.curved`), the quantity the
        noise floor describes: the cut above the floor is measured on them.
    calibration : ScanMetrics or None
        The calibration's own errors on its mesh, when that is not the diagnosis mesh.
    failed : str or None
        Why the final model has no FE solution for this (held-out) scan; ``after`` is
        then None.
    """

    name: str
    role: str
    before: ScanMetrics
    after: ScanMetrics | None
    residual_before_mm: np.ndarray
    residual_after_mm: np.ndarray | None
    calibration: ScanMetrics | None = None
    failed: str | None = None

    def as_json(self, floor_mm: float, *, named: bool = True) -> dict:
        """Surface errors (fiducial frame) and residuals before/after, the cut above the floor.

        ``surface_error_mm`` is the error of every scan vertex to the model's straight
        facets (as ``validate`` reports it); ``residual_mm`` that of the diagnosis' points
        to the curved surface, which the noise floor describes and the cut is measured on.
        With nothing ``named`` the cut is None: "after" is then c1 alone refitted, and the
        ratio of two differences near the floor says nothing about an effect.
        """
        b = self.before.surface_error_mm["fiducial"]
        out = {"role": self.role, "surface_error_mm": {"before": b}, "floor_mm": floor_mm}
        out["nipple_error_mm"] = {"before": self.before.nipple_error_mm.get("fiducial")}
        if self.calibration is not None:
            out["surface_error_mm"]["calibration"] = self.calibration.surface_error_mm["fiducial"]
            out["nipple_error_mm"]["calibration"] = self.calibration.nipple_error_mm.get("fiducial")
        out["residual_mm"] = {"before": _abs_summary(self.residual_before_mm)}
        if self.failed is not None:
            out["failed"] = self.failed
        if self.after is not None:
            a = self.after.surface_error_mm["fiducial"]
            out["surface_error_mm"]["after"] = a
            out["nipple_error_mm"]["after"] = self.after.nipple_error_mm.get("fiducial")
            out["residual_mm"]["after"] = _abs_summary(self.residual_after_mm)
            rb, ra = out["residual_mm"]["before"]["mean"], out["residual_mm"]["after"]["mean"]
            above = rb - floor_mm
            cut = named and above > 1e-9
            out["cut_above_floor"] = float((rb - ra) / above) if cut else None
        return out


def _abs_summary(r: np.ndarray) -> dict:
    """Mean, rms and 95th percentile of ``|r|`` (mm) and the number of points."""
    a = np.abs(np.asarray(r, float))
    rms = float(np.sqrt(np.mean(a**2)))
    return {"mean": float(a.mean()), "rms": rms, "p95": float(np.percentile(a, 95)), "n": a.size}


@dataclass(frozen=True)
class Diagnosis:
    """Everything ``diagnose`` found (see the module docstring).

    Attributes
    ----------
    verdict : str
    named : tuple of str
    confounded_with : tuple of str
    problem : Problem
    null : Refit
        ``ln c1`` alone on the diagnosis scans.
    final : Refit
        The model with the named effects (``null`` when none).
    screen : Screen
        At the null fit.
    final_screen : Screen or None
        Of the remaining effects at the final fit.
    candidates : tuple of Candidate
    maps : dict of str to ScanMap
    gaps : dict of str to ScanGap
    intervals : dict of str to dict
        95 % intervals of the final model's parameters.
    floor_mm2 : float
        Noise floor of the residual's mean square.
    explained_margin_mm : float
        Criterion (d) was judged on the points farther than this from the back plate.
    explained_floor_mm2 : float
        The noise floor on those points (the lowest any model tried leaves).
    unavailable : dict of str to str
    options : DiagnosisOptions
        The options the diagnosis ran with (the defaults where none were given), as
        recorded in :meth:`to_json`'s ``options``.
    wall_s : float
    fe_solves : int
    final_states : dict
        ScanState of every scan at the final model (for the refitted calibration).
    limits : dict of str to ParameterLimit
        Per physical effect not found, its detectable size in its own parameter
        (``parameter_limits``; empty without it).
    mesh_error_record : dict
        ``mesh_error="absorbed"``: ``status`` ("absorbed" or "unavailable"), the coarser
        mesh's ``size_mm``, and either its ``n_tets``, ``factor``, ``effective_factor``,
        ``elements_tall``, ``max_dihedral_deg``, ``note``, the change's ``rms_mm`` per scan
        and the residual's ``amplitude``, ``standard_error``, ``statistic`` and ``shared``
        along it (:class:`calib.discrepancy.screen.MeshErrorCheck`), or the ``reason``;
        empty with ``"ignored"``.
    """

    verdict: str
    named: tuple
    confounded_with: tuple
    problem: Problem
    null: Refit
    final: Refit
    screen: Screen
    final_screen: Screen | None
    candidates: tuple
    maps: dict
    gaps: dict
    intervals: dict
    floor_mm2: float
    unavailable: dict
    options: DiagnosisOptions
    wall_s: float
    fe_solves: int
    final_states: dict = field(repr=False, default_factory=dict)
    explained_margin_mm: float = 0.0
    explained_floor_mm2: float = 0.0
    limits: dict = field(default_factory=dict)
    mesh_error_record: dict = field(default_factory=dict)

    @property
    def c1_pa(self) -> float:
        """The final model's c1 (Pa)."""
        return self.final.c1_pa

    def screening_rows(self) -> list[dict]:
        """One row per screened column: effect, statistic, p, Holm p, significant, ..."""
        scr = self.screen.screening
        if scr is None:
            return []
        return [{k: _num(v) if isinstance(v, float) else v for k, v in vars(e).items()}
                for e in scr.effects]  # fmt: skip

    def effect_summary(self) -> dict:
        """Per library effect: the strongest of its columns and the identifiability."""
        scr = self.screen.screening
        out = {}
        for name in self.options.effects:
            lib = LIBRARY[name]
            rows = [e for e in (scr.effects if scr else ()) if e.effect == name]
            entry = {"kind": lib.kind, "parameter": lib.parameter, "unit": lib.unit,
                     "columns": len(rows)}  # fmt: skip
            if name == "sliding":
                entry["probe_pa_per_mm"] = self.problem.sliding_probe_pa_per_mm
                entry["body_height_mm"] = self.problem.body_height_mm
            if name in self.unavailable:
                entry["status"] = "unavailable"
                entry["reason"] = self.unavailable[name]
            elif not rows:
                entry["status"] = "not screened"
            else:
                tested = [e for e in rows if e.identifiable]
                best = min(tested, key=lambda e: e.p_value) if tested else rows[0]
                entry |= {
                    "status": "identifiable" if tested else "not identifiable",
                    "statistic": _num(best.statistic),
                    "p_value": _num(best.p_value),
                    "p_holm": _num(min((e.p_holm for e in tested), default=np.nan)),
                    "significant": any(e.significant for e in tested),
                    "estimate": _num(best.estimate) if rows and len(rows) == 1 else None,
                    "detectable": _num(best.detectable) if len(rows) == 1 else None,
                    "parameter_limit": self.limits[name].as_json() if name in self.limits else None,
                    "screen_unit": _screen_unit(name, self.problem),
                    "retained_fraction": _num(max(e.retained_fraction for e in rows)),
                }
                if name == "density":
                    entry["note"] = (
                        "at fixed nu the solution depends on rho g / c1 only: its field is "
                        "c1's own, never separable under gravity"
                    )
            out[name] = entry
        return out

    def to_json(self) -> dict:
        """``diagnosis.json`` (without ``run_id``, files and provenance)."""
        prob = self.problem
        floor = float(np.sqrt(max(self.floor_mm2, 0.0)) * np.sqrt(2.0 / np.pi))
        scr = self.screen.screening
        return {
            "verdict": self.verdict,
            "named": list(self.named),
            "confounded_with": list(self.confounded_with),
            "calibration": {
                "c1_pa": float(np.exp(prob.theta_calibrated)),
                "run_id": prob.work.record.get("run_id"),
                "mesh_note": prob.mesh_note or None,
            },
            "model_mesh": {
                "size_mm": prob.mesh_size_mm,
                "max_dihedral_deg": prob.mesh_max_dihedral_deg,
                "n_tets": prob.mesh.n_tets,
                "facet_gap_mm": prob.facet_gap_mm(),
                "error": self.mesh_error_record or None,
                "inclusions": len(prob.inclusions),
                "inclusions_left_out": inclusions_left_out(prob.work),
            },
            "scans": {
                "diagnosis": list(prob.scans),
                "holdout": prob.holdout,
                "excluded": failed_scans(prob.work),
                "imaging_noise_mm": prob.imaging_noise_mm,
                "rim_margin_mm": prob.rim_margin_mm,
                "region_scale": prob.region_scale,
                "explained_margin_mm": self.explained_margin_mm,
            },
            "null_fit": _fit_json(self.null),
            "refit": _fit_json(self.final) | {"intervals": self.intervals},
            "c1_pa": self.final.c1_pa,
            "c1_ci95_pa": self.intervals.get("theta", {}).get("c1_ci95_pa"),
            "noise": {
                "model": self.screen.noise.best.as_json(),
                "plausible": [m.as_json() for m in self.screen.noise.plausible],
                "scan_sd_mm": _scan_levels(self.screen.noise, self.null.fields.scans),
                "by_scan": self.screen.noise.by_scan,
                "floor_rms_mm": float(np.sqrt(max(self.floor_mm2, 0.0))),
                "floor_mean_abs_mm": floor,
                "floor_max_lag_mm": FLOOR_LAG_MM * prob.region_scale,
                "explained_floor_rms_mm": float(np.sqrt(max(self.explained_floor_mm2, 0.0))),
                "height_profile": None if prob.profile is None else prob.profile.as_json(),
            },
            "misfit_test": self.screen.misfit.as_json(),
            "effects": self.effect_summary(),
            "screening": {
                "columns": self.screening_rows(),
                "confounded": [list(c) for c in scr.confounded] if scr else [],
                "cosine": None
                if scr is None
                else np.where(np.isfinite(scr.cosine), np.round(scr.cosine, 4), None).tolist(),
                "not_identifiable": list(scr.not_identifiable) if scr else [],
                "alpha": self.options.alpha,
                "metric": scr.metric if scr else None,
            },
            "final_screening": None
            if self.final_screen is None or not self.final_screen.screening
            else {
                "misfit_test": self.final_screen.misfit.as_json(),
                "columns": [
                    {k: _num(v) if isinstance(v, float) else v for k, v in vars(e).items()}
                    for e in self.final_screen.screening.effects
                ],
            },  # fmt: skip
            "candidates": [c.as_json() for c in self.candidates],
            "localisation": {n: m.as_json() for n, m in self.maps.items()},
            "gap": {n: g.as_json(floor, named=bool(self.named)) for n, g in self.gaps.items()},
            "unavailable": self.unavailable,
            "library": {n: LIBRARY[n].as_json() for n in self.options.effects},
            "options": {
                k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self.options).items()
            },  # fmt: skip
            "fe_solves": self.fe_solves,
            "wall_s": self.wall_s,
        }


def _fit_json(fit: Refit) -> dict:
    return {
        "effects": list(fit.effects),
        "c1_pa": fit.c1_pa,
        "parameters": {n: float(v) for n, v in zip(fit.names[1:], fit.x[1:], strict=True)},
        "values": fit.values.as_json(),
        "rms_mm": float(np.sqrt(fit.mean_sq_mm2)),
        "iterations": fit.iterations,
        "evaluations": fit.evaluations,
        "failed_evaluations": fit.failed_evaluations,
        "success": fit.success,
        "message": fit.message,
        "at_bound": list(fit.at_bound()),
    }


# ------------------------------------------------------------------------ helpers


def _centred_ms(fields: FieldSet, keep: dict | None = None) -> float:
    """Mean square of the residuals less each scan's mean (mm^2).

    ``keep``: per scan, a boolean mask of the points to use (default all); a scan's mean
    is that of its kept points.
    """
    res = fields.residual
    kept = {n: r if keep is None else r[keep[n]] for n, r in res.items()}
    tot = sum(float(np.sum((r - r.mean()) ** 2)) for r in kept.values() if len(r))
    return tot / sum(len(r) for r in kept.values())


def _judged_points(prob: Problem, margin: float | Literal["element"]) -> tuple[float, dict]:
    """The points criterion (d) is judged on: farther than ``margin`` from the back plate.

    ``"element"`` is one model element (:func:`calib.discrepancy.problem.rim_margin_of`).
    A margin that would leave fewer than half of a scan's diagnosed points is lowered to
    the smallest scan median of the points' heights, so that every scan keeps half (it is
    said in the progress and recorded as ``scans.explained_margin_mm``).

    Returns
    -------
    margin_mm : float
    keep : dict of str to ndarray of bool
        Per diagnosis scan, the points judged, in the order of ``prob.points``.
    """
    want = rim_margin_of(prob.mesh_size_mm, margin)
    heights = {n: plate_height_mm(prob.measurement(n), prob.points[n]) for n in prob.scans}
    mm = min(want, min(float(np.median(h)) for h in heights.values()))
    return mm, {n: h >= mm for n, h in heights.items()}


def _screen_options(o: DiagnosisOptions, prob: Problem) -> dict:
    """:func:`calib.discrepancy.screen.screen`'s options of every screen of a diagnosis."""
    return {
        "alpha": o.alpha,
        "misfit_alpha": o.misfit_alpha,
        "confounded_above": o.confounded_above,
        "by_scan": prob.imaged_unlike,  # each scan at its own noise level
        "max_lag_mm": NOISE_LAG_MM * prob.region_scale,
    }


def _scan_levels(noise: NoiseFit, scans) -> dict:
    """Each scan's noise level (mm, ``NoiseFit.scan_sd_mm``) by name (``scans``' order)."""
    return {n: float(noise.scan_sd_mm[k]) for k, n in enumerate(scans)}


def _noise_var(fields: FieldSet, prob: Problem, keep: dict | None = None) -> float:
    """The session's short-range noise variance (FLOOR_LAG_MM variogram), centred residual.

    Averaged over the points, each scan's at its own level where the scans are imaged
    unlike (:attr:`Problem.imaged_unlike`, :meth:`calib.stats.NoiseFit.variance_mm2`).

    ``keep``: per scan, a boolean mask of the points to use (default all).
    """
    points = prob.points
    if keep is not None:
        points = {n: points[n][keep[n]] for n in fields.scans}
        kept = {n: fields.residual[n][keep[n]] for n in fields.scans}
        fields = replace(fields, residual=kept)
    sample = sample_of(fields, points)
    r = np.concatenate([fields.residual[n] - fields.residual[n].mean() for n in fields.scans])
    lag = FLOOR_LAG_MM * prob.region_scale
    fit = session_noise(sample, r, max_lag_mm=lag, by_scan=prob.imaged_unlike)
    return fit.variance_mm2(sample)


def _effect_of(column: str) -> str:
    return column.split("[", 1)[0]


def _significant_effects(scr: Screen) -> list[tuple[str, float, float]]:
    """``(effect, |t|, p_holm)`` of effects with a significant column, strongest first."""
    if scr.screening is None:
        return []
    best: dict = {}
    for e in scr.screening.effects:
        if e.identifiable and e.significant:
            eff = e.effect
            if eff not in best or abs(e.statistic) > best[eff][0]:
                best[eff] = (abs(e.statistic), e.p_holm)
    return sorted(((k, v[0], v[1]) for k, v in best.items()), key=lambda t: -t[1])


def _cosine(scr: Screen, a: str, b: str) -> float:
    """Largest |cos| between the projected signatures of two effects' columns."""
    s = scr.screening
    if s is None:
        return 0.0
    ia = [i for i, e in enumerate(s.effects) if e.effect == a]
    ib = [i for i, e in enumerate(s.effects) if e.effect == b]
    vals = [abs(s.cosine[i, j]) for i in ia for j in ib if np.isfinite(s.cosine[i, j])]
    return float(max(vals, default=0.0))


def _columns_of(fields: FieldSet, effects: Sequence[str]) -> tuple[str, ...]:
    return tuple(c.name for c in fields.columns if c.effect in effects)


# ------------------------------------------------------------------------- diagnose


def diagnose(
    work: WorkFolder | str | Path,
    options: DiagnosisOptions | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> Diagnosis:
    """Diagnose a calibrated work folder (see the module docstring).

    Parameters
    ----------
    work : WorkFolder, str, Path or calib.notebook.Work
        :func:`calib.data.read_work`, a path to read, or ``calib.load_work``'s object.
    options : DiagnosisOptions, optional
    progress : callable, optional
        Called with a line of text at every step.

    Returns
    -------
    Diagnosis

    Raises
    ------
    DiagnosisError
        Bad options or a work folder the diagnosis cannot use.
    fem.ConvergenceError
        No FE solution at the calibration's own c1 (the null fit cannot start).
    """
    o = options or DiagnosisOptions()
    say = progress or log.info
    t0 = time.perf_counter()
    work = as_work_folder(work)
    prob = build_problem(
        work,
        holdout=o.holdout,
        skin_thickness_mm=o.skin_thickness_mm,
        max_points=o.max_points,
        rim_margin_mm=o.rim_margin_mm,
        mesh_size_mm=o.mesh_size_mm,
        inclusion_mesh_mm=o.inclusion_mesh_mm,
        say=say,
    )
    say(f"diagnosis scans {', '.join(prob.scans)}, held out: {prob.holdout or 'none'}; model mesh "
        f"{prob.mesh.n_tets} tets, {len(prob.inclusions)} inclusions tagged; points within "
        f"{prob.rim_margin_mm:g} mm of the back plate mapped, not diagnosed")  # fmt: skip
    if prob.mesh_note:
        say(f"  {prob.mesh_note}")
    screened = tuple(e for e in o.effects)
    say("null fit: ln c1 alone on the diagnosis scans (full FE)")
    null = refit(prob, (), screened=screened, max_iterations=o.refit_iterations, say=say)
    unavailable = dict(null.fields.unavailable)
    say(f"  c1 = {null.c1_pa:.1f} Pa (calibration {np.exp(prob.theta_calibrated):.1f} Pa), "
        f"rms {np.sqrt(null.mean_sq_mm2):.3f} mm")  # fmt: skip
    if o.noise_profile == "plate":
        prob = replace(prob, profile=_height_profile(prob, null.fields))
        rel = ", ".join(f"{v:.2f}" for v in prob.profile.relative_sd)
        say(
            f"noise by height above the plate, relative to beyond "
            f"{prob.profile.edges_mm[-2]:g} mm: {rel}; null fit again, weighted"
        )
        null = refit(
            prob,
            (),
            screened=screened,
            theta0=null.theta,
            max_iterations=o.refit_iterations,
            say=say,
        )
        unavailable = dict(null.fields.unavailable)
    mesh_error: dict = {}
    if o.mesh_error == "absorbed":
        prob, null, mesh_error = _absorb_mesh_error(work, prob, null, o, say)
    if not null.success:
        say(f"  the null fit did not converge: {null.message}")
    if none_tested := _none_testable(o.effects, unavailable):
        log.warning(none_tested)
    kw = _screen_options(o, prob)
    scr0 = screen(null.fields, prob.points, **kw)
    nb = scr0.noise.best
    say(f"noise: {nb.kernel}, sd {nb.sigma_mm:.3f} mm, length {nb.length_mm:.1f} mm; misfit "
        f"test p = {scr0.misfit.p_value:.3g} ({scr0.misfit.verdict})")  # fmt: skip
    if scr0.noise.by_scan:
        levels = _scan_levels(scr0.noise, null.fields.scans)
        log.warning(
            "the scans are imaged unlike (voxel size x image noise: %s): each is tested, "
            "mapped and floored at its own noise level (%s, from its shortest lags), with "
            "the correlation of the quietest, or its own where that is more conservative",
            ", ".join(f"{n} {v:.3g}" for n, v in prob.imaging_noise_mm.items()),
            ", ".join(f"{n} {v:.3f} mm" for n, v in levels.items()),
        )
    if check := mesh_error_check(null.fields, prob.points, scr0.noise):
        mesh_error |= check.as_json()
        say(f"  the residual along it: {mesh_error_reading(mesh_error)}")
    maps = _localise(prob, null, scr0.noise)
    floor = _noise_var(null.fields, prob)
    judged_beyond, judged = _judged_points(prob, o.explained_margin_mm)
    floor_judged = _noise_var(null.fields, prob, judged)
    n_judged = sum(int(m.sum()) for m in judged.values())
    n_all = sum(len(m) for m in judged.values())
    want = rim_margin_of(prob.mesh_size_mm, o.explained_margin_mm)
    lowered = (
        f" (not {want:.3g} mm: that would leave a scan fewer than half its points)"
        if judged_beyond < want
        else ""
    )
    say(
        f"the share of the residual an effect explains, judged on the {n_judged} of {n_all} points "
        f"beyond {judged_beyond:.3g} mm of the back plate{lowered}"
    )
    named, confounded, candidates, current, cur_scr = [], [], [], null, scr0
    fits: dict = {(): null}
    rnd = 0
    while len(named) < o.max_named:
        rnd += 1
        sig = [s for s in _significant_effects(cur_scr) if s[0] not in named]
        if not sig:
            break
        stages = _candidates(sig, partial(_cosine, cur_scr), o)
        row = {s[0]: s for s in sig}
        passing, trials = [], {}
        for chosen in stages:  # physical effects first, nuisances if none passes
            if passing or not chosen:
                continue
            each = "each " if len(chosen) > 1 else ""
            jointly = ", ".join(["c1", *named])  # review BC: from round 2 the named ones too
            say(f"round {rnd}: refitting {', '.join(chosen)}, {each}jointly with {jointly} "
                "(full FE)")  # fmt: skip
            for eff in chosen:
                key = tuple(sorted([*named, eff]))
                try:
                    trials[eff] = fits.get(key) or refit(
                        prob, key, screened=screened, theta0=current.theta,
                        x0=dict(zip(current.names, current.x, strict=True)),
                        max_iterations=o.refit_iterations, say=say,
                    )  # fmt: skip
                except fem.ConvergenceError as exc:
                    say(f"  {eff}: no FE solution at the start ({exc})")
                    continue
                fits[key] = trials[eff]
                floor = min(floor, _noise_var(trials[eff].fields, prob))
                floor_judged = min(floor_judged, _noise_var(trials[eff].fields, prob, judged))
            floors = (floor, floor_judged, judged)
            round_ = [_judge(prob, eff, rnd, row[eff], current, trials[eff], floors, o)
                      for eff in chosen if eff in trials]  # fmt: skip
            round_ += [_not_refitted(eff, rnd, row[eff]) for eff in chosen if eff not in trials]
            candidates.extend(round_)
            passing = sorted((c for c in round_ if c.passes), key=lambda c: -c.explained)
            for c in round_:
                if not np.isfinite(c.c1_pa):
                    say(f"  {c.effect}: not refitted ({c.reason})")
                    continue
                say(f"  {c.effect}: c1 = {c.c1_pa:.1f} Pa, explains {c.explained:.0%} above "
                    f"the floor, leave-one-posture-out prediction {_lopo_word(c)}"
                    + ("" if c.passes else f"; not named ({c.reason})"))  # fmt: skip
        if not passing:
            break
        best = passing[0]
        if not named:
            confounded = [
                c.effect
                for c in passing[1:]
                if c.explained >= o.near_equal * best.explained
                and _cosine(cur_scr, c.effect, best.effect) >= o.confounded_above
            ]
        named.append(best.effect)
        current = trials[best.effect]
        absorbed = _columns_of(current.fields, named)
        cur_scr = screen(current.fields, prob.points, absorbed=absorbed, **kw)
        if len(named) >= 2:
            named, current, cur_scr = _prune(prob, named, fits, current, cur_scr, o, screened, say)
    final_screen = cur_scr if named else None
    verdict = _verdict(named, confounded, scr0, final_screen, o)
    say(f"verdict: {verdict}")
    limits = {}
    if o.parameter_limits:
        # at the final model: what its screen would have found besides the named effects
        lost = [e for e in screened if e not in named]
        absorbed = _columns_of(current.fields, named)
        limits = parameter_limits(prob, current, cur_scr, lost, absorbed=absorbed, say=say)
    gaps, states = _gaps(prob, null, current, say)
    intervals = _intervals(current, prob)
    return Diagnosis(
        verdict=verdict, named=tuple(named), confounded_with=tuple(confounded), problem=prob,
        null=null, final=current, screen=scr0, final_screen=final_screen,
        candidates=tuple(candidates), maps=maps, gaps=gaps, intervals=intervals,
        floor_mm2=floor, unavailable=unavailable, options=o,
        wall_s=time.perf_counter() - t0, fe_solves=int(prob.fm.solves), final_states=states,
        explained_margin_mm=judged_beyond, explained_floor_mm2=floor_judged, limits=limits,
        mesh_error_record=mesh_error,
    )  # fmt: skip


def _lopo_word(c: Candidate) -> str:
    """The leave-one-posture-out criterion as judged: a nuisance's need only not worsen."""
    if LIBRARY[c.effect].kind == "nuisance":  # _judge: la <= lb (review BC)
        return "not worse" if c.lopo_improves else "worse"
    return "better" if c.lopo_improves else "not better"


def _absorb_mesh_error(
    work: WorkFolder, prob: Problem, null: Refit, o: DiagnosisOptions, say
) -> tuple[Problem, Refit, dict]:
    """The model mesh's discretisation column on the problem and the null fit's fields.

    Returns ``(prob, null, record)``; where the coarser mesh cannot be built or solved,
    ``prob`` and ``null`` unchanged and the record says why (a warning too).
    """
    size = round(COARSER_FACTOR * prob.mesh_size_mm, 1)
    say(f"the model mesh's own error: the null fit's c1 on a {size:g} mm mesh")
    try:
        coarse = build_problem(
            work,
            holdout=o.holdout,
            skin_thickness_mm=o.skin_thickness_mm,
            max_points=o.max_points,
            rim_margin_mm=prob.rim_margin_mm,  # the model's band (its points are used)
            mesh_size_mm=size,
            inclusion_mesh_mm=o.inclusion_mesh_mm,
            say=say,
        )
        d = discretisation_field(prob, coarse, null.theta, null.fields.residual)
    except (ValueError, fem.ConvergenceError, np.linalg.LinAlgError) as exc:
        why = f"no model on a {size:g} mm mesh: {exc}"
        say(f"  not absorbed: {why}")
        log.warning("the model mesh's error is not absorbed: %s", why)
        return prob, null, {"status": "unavailable", "size_mm": size, "reason": why}
    prob = replace(prob, discretisation=d)
    fields = null.fields
    col = discretisation_column(prob, fields.scans)
    null = replace(null, fields=replace(fields, columns=(*fields.columns, col)))
    rms = {n: float(np.sqrt(np.mean(v**2))) for n, v in d.items()}
    effective = float((prob.mesh.n_tets / coarse.mesh.n_tets) ** (1.0 / 3.0))
    tall = float(prob.body_height_mm / size) if prob.body_height_mm else None
    say(
        f"  {coarse.mesh.n_tets} tets (effective factor {effective:.2f}); the residual "
        "change, rms: " + ", ".join(f"{n} {v:.3f} mm" for n, v in rms.items())
    )
    if tall is not None and tall < 2.0:
        say(f"  the coarser mesh is {tall:.1f} elements tall: its change is a rough direction")
    return (
        prob,
        null,
        {
            "status": "absorbed",
            "size_mm": size,
            "n_tets": int(coarse.mesh.n_tets),
            "factor": COARSER_FACTOR,
            "effective_factor": effective,
            "elements_tall": tall,
            "max_dihedral_deg": coarse.mesh_max_dihedral_deg,
            "note": coarse.mesh_note or None,
            "rms_mm": rms,
        },
    )


#: A residual along the discretisation column below this |t| does not carry it.
MESH_ERROR_MIN_T = 2.0
#: From this |cos| an effect's signature is said to be shared with the column.
MESH_ERROR_SHARED = 0.5


def mesh_error_reading(check: dict) -> str:
    """The residual's amplitude along the discretisation column, read, and what it shares.

    ``check``: :meth:`calib.discrepancy.screen.MeshErrorCheck.as_json` (as in
    ``diagnosis.json``'s ``model_mesh.error``). The one phrase of the progress and the
    summary.
    """
    a, t = check["amplitude"], check["statistic"]
    said = f"amplitude {a:.2f} +- {check['standard_error']:.2f} (t {t:.1f}): "
    if abs(t) < MESH_ERROR_MIN_T:
        said += (
            f"the residual has little along it (|t| < {MESH_ERROR_MIN_T:g}): absorbing it "
            "changes little"
        )
    elif a > 0:
        said += (
            f"as the model mesh's error of a converging order p would carry it (1 / "
            f"({COARSER_FACTOR:g}^p - 1): 1.04 for p = 2, 2.5 for p = 1)"
        )
    else:
        said += (
            "the coarser mesh fits better along it: the mesh dependence is not monotone "
            "here, so the column is a direction of mesh dependence, not an estimate of the "
            "error"
        )
    shared = [f"{k} (|cos| {v:.2f})" for k, v in check["shared"].items() if v >= MESH_ERROR_SHARED]
    return said + ("; it shares its direction with " + ", ".join(shared) if shared else "")


def _height_profile(prob: Problem, fields: FieldSet):
    """The residual's spread by height above the plate, pooled over the diagnosis scans.

    Each scan's residual is centred by its median beyond 20 mm (a scan's offset is a
    nuisance, not spread).
    """
    heights, resid = [], []
    for n in fields.scans:
        h = plate_height_mm(prob.measurement(n), prob.points[n])
        r = fields.residual[n]
        far = h >= 20.0
        resid.append(r - np.median(r[far] if far.any() else r))
        heights.append(h)
    try:
        return height_profile(np.concatenate(heights), np.concatenate(resid))
    except ValueError as exc:
        raise DiagnosisError(f"{prob.work.path}: no noise profile by height ({exc})") from exc


def _candidates(sig, cosine, o) -> list[list[str]]:
    """The effects a round refits, physical ones first.

    Stage one holds the ``o.max_candidates`` strongest significant physical effects (every
    kind but ``nuisance``) that can be refitted, plus any significant effect whose
    signature is confounded with one of them; stage two the nuisances, chosen the same
    way, refitted only when no stage-one candidate passes. A per-scan nuisance (a gravity
    angle, a rigid offset) is the explanation of last resort: it has parameters of its
    own in every scan and can absorb a physical effect's print on one posture, while a
    physical effect must predict every posture with one value; the next round screens
    the nuisances again at the model with the physical effect in it.

    Parameters
    ----------
    sig : list of (effect, abs score, Holm p)
        Significant effects, strongest first (:func:`_significant_effects`).
    cosine : callable
        ``cosine(a, b)``: the largest |cos| between two effects' projected signatures.
    o : DiagnosisOptions

    Returns
    -------
    stages : list of two lists of str
        The physical candidates, then the nuisances.
    """
    stages = []
    for nuisance in (False, True):
        refittable = [s[0] for s in sig if (LIBRARY[s[0]].kind == "nuisance") == nuisance]
        chosen = refittable[: o.max_candidates]
        for eff in refittable[o.max_candidates :]:  # a confounded partner joins
            if any(cosine(eff, c) >= o.confounded_above for c in chosen):
                chosen.append(eff)
        stages.append(chosen)
    return stages


def _not_refitted(eff: str, rnd: int, sig_row) -> Candidate:
    """A significant effect that could not be refitted (so not named)."""
    _, stat, p_holm = sig_row
    why = "no FE solution at the refit's start"
    return Candidate(eff, rnd, True, float(p_holm), float(stat), None, None, False, {}, (),
                     False, float("nan"), False, float("nan"), float("nan"), why)  # fmt: skip


def _registration_excess(prob: Problem, fit: Refit) -> list[str]:
    """Scans whose fitted rigid offset moves a point farther than its registration allows."""
    out = []
    for n in prob.scans:
        off = fit.nuisance[n].offset
        arm = prob.points[n] - prob.centres[n]
        move = float(np.linalg.norm(off[:3] + np.cross(off[3:], arm), axis=1).max())
        if move > prob.registration_tolerance_mm[n]:
            out.append(f"{n}: offset moves points {move:.2f} mm, its registration allows "
                       f"{prob.registration_tolerance_mm[n]:.2f} mm")  # fmt: skip
    return out


def _gravity_excess(prob: Problem, fit: Refit) -> list[str]:
    """Scans whose fitted gravity angle exceeds the rotation their registration allows.

    A scan's gravity in the reference frame is the scanner's (``session.toml``, taken as
    exact) turned by the scan's registered rotation, so its error is that rotation's: a
    rotation by ``t`` moves the scan's farthest measured point (distance ``R`` from the
    centre) by about ``R t``, and the registration allows ``tolerance / R``
    (:attr:`Problem.registration_tolerance_mm`, the rigid offsets' bound).
    """
    out = []
    for n in prob.scans:
        angle = float(np.linalg.norm(fit.nuisance[n].gravity_rad))
        arm = float(np.linalg.norm(prob.points[n] - prob.centres[n], axis=1).max())
        allowed = prob.registration_tolerance_mm[n] / arm
        if angle > allowed:
            turned, limit = np.degrees(angle), np.degrees(allowed)
            out.append(
                f"{n}: gravity turned {turned:.2f} deg, its registration allows {limit:.2f} deg"
            )
    return out


#: A candidate that makes the residual beyond one element from the plate worse by more
#: than this share of its excess over the noise floor is not named, whatever it explains
#: on every point (review BO: the every-point share lets an effect that fits the clamped
#: rim's misfit pass; on an independent FE code's scans that misfit is not the model's
#: own, and a doubled misfit over the body is no explanation of it)
MAX_WORSENED_BEYOND = 0.1


def _judge(prob, eff, rnd, sig_row, before: Refit, after: Refit, floors: tuple, o) -> Candidate:
    """The naming criteria of one refitted candidate.

    Per-scan nuisances (gravity, registration) cannot be learnt from the other postures,
    so for them criterion (b) is that the leave-one-posture-out prediction does not get
    worse; a rigid offset or a gravity angle is plausible only within its scan's
    registration tolerance (:func:`_registration_excess`, :func:`_gravity_excess`).
    """
    _, stat, p_holm = sig_row
    lb, la = lopo(before)["mean_sq_mm2"], lopo(after)["mean_sq_mm2"]
    nuisance = LIBRARY[eff].kind == "nuisance"
    lopo_ok = la is not None and lb is not None and (la <= lb if nuisance else la < lb)
    own = [n for n in after.names if _effect_of(n) == eff]
    params = {n: after.parameter(n) for n in own}
    bound = tuple(n for n in after.at_bound() if n in own)
    excess = {"registration": _registration_excess, "gravity": _gravity_excess}.get(eff)
    implausible = excess(prob, after) if excess else []
    floor, floor_judged, judged = floors
    explained_all = _explained(before.fields, after.fields, floor, None)
    beyond = _explained(before.fields, after.fields, floor_judged, judged)
    # a physical effect may act at the plate itself (a sliding plate does); the
    # explanation of last resort is held to the stricter share
    explained = (min if nuisance else max)(beyond, explained_all)
    reasons = []
    if beyond < -MAX_WORSENED_BEYOND:
        # review BO: an effect that removes the rim's misfit (another FE code's clamped
        # edge is not the model's) while the body beyond it gets worse is no explanation
        reasons.append(f"worsens the fit beyond the plate's element (explains {beyond:.0%} there)")
    if not lopo_ok:
        what = "gets worse" if nuisance else "does not improve"
        reasons.append(f"leave-one-posture-out prediction {what}"
                       if la is not None else "leave-one-posture-out needs >= 2 scans")  # fmt: skip
    low = after.at_lower_bound()
    if eff == "sliding" and "sliding" in low:
        # review BO: the refit's softest springs are where the model stops solving, not the
        # end of the effect's range (a frictionless plate, k = 0, lies past them)
        reasons.append(
            f"springs at the refit's softest, {np.exp(after.parameter('sliding')):.3g} Pa/mm "
            f"(the probe x {SLIDING_PROBE_MULTIPLES[0]:g}, where the model stops solving): "
            "the data ask for a plate as free or freer, which the model cannot fit"
        )
    elif eff == "skin" and "skin" in bound and "skin" not in low:
        # review BO: a skin stiffer or thicker than the band's range holds (an excess of
        # 99 x the band) has no way out but another band; say which
        t = prob.skin_thickness_mm
        wider = (
            f"--skin-thickness {min(2 * t, 10.0):g} widens what it can fit"
            if t < 10.0
            else "the band is at its widest (10 mm)"
        )
        reasons.append(
            f"skin ratio at the top of its range ({1 + after.parameter('skin'):.3g} on the "
            f"assumed {t:g} mm band): a thicker, stiffer skin than the band holds; {wider}"
        )
    elif bound:
        reasons.append(f"parameter at a bound of its physical range ({', '.join(bound)})")
    if implausible:
        reasons.append("implausible (" + "; ".join(implausible) + ")")
    if explained < o.min_explained:
        reasons.append(f"explains {explained:.0%} < {o.min_explained:.0%} of the residual "
                       "above the noise floor")  # fmt: skip
    if not after.success:
        reasons.append(f"refit did not converge ({after.message})")
    return Candidate(
        effect=eff,
        round=rnd,
        significant=True,
        p_holm=float(p_holm),
        statistic=float(stat),
        lopo_before_mm2=lb,
        lopo_after_mm2=la,
        lopo_improves=lopo_ok,
        parameters=params,
        at_bound=bound,
        plausible=not bound and not implausible,
        explained=float(explained),
        passes=not reasons,
        c1_pa=after.c1_pa,
        rms_mm=float(np.sqrt(after.mean_sq_mm2)),
        reason="; ".join(reasons),
        explained_all_points=float(explained_all),
    )


def _explained(before: FieldSet, after: FieldSet, floor: float, keep: dict | None) -> float:
    """``(MS_before - MS_after) / (MS_before - floor)`` on the ``keep`` points (0 at the floor)."""
    ms_b, ms_a = _centred_ms(before, keep), _centred_ms(after, keep)
    excess = ms_b - floor
    return (ms_b - ms_a) / excess if excess > 0 else 0.0


def _prune(prob, named, fits, current, cur_scr, o, screened, say):
    """Backward pruning: drop a named effect that is not significant without it."""
    for eff in list(named):
        rest = tuple(sorted(e for e in named if e != eff))
        fit = fits.get(rest)
        if fit is None:
            fit = refit(prob, rest, screened=screened, theta0=current.theta,
                        max_iterations=o.refit_iterations, say=say)  # fmt: skip
            fits[rest] = fit
        kw = _screen_options(o, prob)
        scr = screen(fit.fields, prob.points, absorbed=_columns_of(fit.fields, rest), **kw)
        if eff not in [s[0] for s in _significant_effects(scr)]:
            say(f"pruned {eff}: not significant once {', '.join(rest)} is in the model")
            named = [e for e in named if e != eff]
            current = fit
            cur_scr = scr
            break
    return named, current, cur_scr


def _none_testable(effects, unavailable: dict) -> str | None:
    """What to say when none of the effects asked for can be tested (None: some can)."""
    if not effects or not set(effects) <= set(unavailable):
        return None
    why = "; ".join(f"{e}: {unavailable[e]}" for e in effects)
    tail = "the verdict rests on the misfit test alone"
    return f"none of the effects asked for can be tested ({why}): {tail}"


def _verdict(named, confounded, scr0: Screen, final: Screen | None, o) -> str:
    if named:
        head = named[0] + (" | " + " | ".join(confounded) + " (confounded)" if confounded else "")
        if len(named) > 1:
            head = " + ".join(named)
        left = final is not None and (
            final.misfit.verdict == "misfit" or _significant_effects(final)
        )
        return f"named: {head}" + (" (+ unexplained remainder)" if left else "")
    lost = scr0.screening.not_identifiable if scr0.screening else ()
    identifiable = [e for e in o.effects if not any(_effect_of(n) == e for n in lost)]
    if scr0.misfit.verdict == "fits" and not _significant_effects(scr0):
        return "no missing effect"
    if not identifiable and lost:
        return "not identifiable from these data: " + ", ".join(
            dict.fromkeys(_effect_of(n) for n in lost)
        )
    return "unexplained"


def _localise(prob: Problem, null: Refit, noise: NoiseFit) -> dict:
    """Significance maps of the diagnosis scans at the null fit.

    The maps take in the points within the rim margin too (:attr:`Problem.rim_points`:
    never fitted nor tested, but where the model misfits most); the ``rim`` region is
    then the band the diagnosis leaves out, or 10 mm where the margin is narrower.
    Residuals are centred by the mean of the diagnosed points, as the fit sees them.
    """
    rim = {n: p for n, p in prob.rim_points.items() if n in null.fields.scans and len(p)}
    states = {}
    if rim:  # the null fit's states again (warm: the forward model keeps them)
        states = prob.solve(null.theta, null.values, list(rim), gradient=False,
                            nuisance=null.nuisance)  # fmt: skip
    out = {}
    arg = noise.best_arg
    for label, n in enumerate(null.fields.scans):  # the screen's labels (sample_of)
        model = arg if isinstance(arg, NoiseModel) else arg[label]
        r = null.fields.residual[n]
        centre = r.mean()
        pts = prob.points[n]
        if n in rim:
            pos = states[n].positions_mm
            r_rim = prob.residuals(n, pos, None, null.nuisance.get(n), points_mm=rim[n]).r
            pts, r = np.vstack([pts, rim[n]]), np.concatenate([r, r_rim])
        labels = _scan_regions(prob, n, pts)
        out[n] = significance_map(n, pts, r - centre, labels, model,
                                  bandwidth_mm=MAP_KERNEL_MM * prob.region_scale)  # fmt: skip
    return out


def _scan_regions(prob: Problem, name: str, points_mm: np.ndarray) -> np.ndarray:
    """The localisation region of each of a scan's points (reference frame, mm).

    Over inclusions: those ingest segmented in that scan, and its tumour landmark as a
    10 mm sphere; the rim: the band the diagnosis leaves out, or 10 mm where the margin
    is narrower (:func:`calib.discrepancy.localise.region_labels`). Every length but the
    margin and the inclusions' own diameters is scaled by the body's height
    (:func:`calib.model.reference.body_scale`). Shape (n,) of str.
    """
    s = prob.measurement(name)
    doc = ingest_record(prob.work, name)
    T = s.T_ref_from_scan
    spheres = [
        (T[:3, :3] @ np.asarray(i["centre_lps_mm"], float) + T[:3, 3], float(i["diameter_mm"]))
        for i in doc.get("inclusions") or []
    ]
    k = prob.region_scale
    if s.tumour_mm is not None:
        spheres.append((s.tumour_mm, TUMOUR_MM * k))
    radii = region_radii_mm(k, prob.rim_margin_mm)
    return region_labels(
        points_mm,
        nipple_mm=s.nipple_mm,
        back_point_mm=s.back_point_mm,
        back_normal=s.back_normal,
        spheres=spheres,
        apex_mm=radii["apex"],
        rim_mm=radii["rim"],
        over_mm=radii["inclusions"],
    )


def _gaps(prob: Problem, null: Refit, final: Refit, say) -> tuple[dict, dict]:
    """Every scan (holdout included) before and after the named effects, on one mesh.

    Before is c1 alone, after the final model. On the calibration's own mesh c1 alone is
    the calibration's saved states; where the diagnosis runs on another mesh
    (:attr:`Problem.mesh_note`) it is the null fit solved there, so the change from
    before to after is the named effects' and not the mesh's. The calibration's own
    errors on its mesh are then kept beside (``ScanGap.calibration``). A held-out scan
    the final model has no FE solution for (the diagnosis scans solved in every refit;
    it never did) keeps its before, with the reason (``ScanGap.failed``); where c1 alone
    has no solution for it on the diagnosis mesh either, its before is the calibration's.
    """
    from ..model.residuals import SimulatedSurface

    names = [*prob.scans, *([prob.holdout] if prob.holdout else [])]
    say(f"final model on {len(names)} scans (held out: {prob.holdout or 'none'})")

    def solve(fit: Refit, which: list) -> dict:
        nz = {n: fit.nuisance.get(n) for n in which}
        return prob.solve(fit.theta, fit.values, which, gradient=True,
                          nuisance={k: v for k, v in nz.items() if v is not None})  # fmt: skip

    failed = None
    try:
        states = solve(final, names)
    except fem.ConvergenceError as exc:
        if not prob.holdout:
            raise
        failed = f"no FE solution with the final model ({exc})"
        say(f"  {prob.holdout} (held out): {failed}")
        states = solve(final, list(prob.scans))
    work = prob.work
    cal_sim = prob.sim if prob.same_mesh else SimulatedSurface.of(work.mesh)
    if prob.same_mesh:
        null_states = None
    else:
        say("c1 alone on the diagnosis mesh (the gap's before)")
        if null is final:
            null_states = states
        else:
            try:
                null_states = solve(null, names)
            except fem.ConvergenceError:
                if failed is None:
                    raise
                null_states = solve(null, list(prob.scans))
            # the final model last: the refit's files take its stress-free geometry and
            # derivative from the forward model's last recovery (review AU: the null fit's
            # was left there, and a sweep of the refit was 1.2-1.5 mm off its states).
            # Warm-started from its own states and recovery: a few Newton steps
            states = solve(final, list(states))
    out = {}
    for n in names:
        scan = prob.measurement(n)
        saved = work.states[n]
        calibration = scan_metrics(scan, saved.positions_mm, cal_sim.faces, work.nipple_node,
                                   saved.tumour_mm)  # fmt: skip
        after = ra = None
        if n in states:
            pos = states[n].positions_mm
            after = scan_metrics(scan, pos, prob.sim.faces, prob.nipple_node, None)
            # a named rigid offset moves the scan's points (as in the fit); gravity: states
            ra = prob.residuals(n, pos, nuisance=final.nuisance.get(n)).r
        if null_states is None or n not in null_states:  # (the latter: a failed holdout)
            before = calibration
            rb = prob.residuals(n, saved.positions_mm).r
        else:
            pos = null_states[n].positions_mm
            before = scan_metrics(scan, pos, prob.sim.faces, prob.nipple_node, None)
            rb = prob.residuals(n, pos).r
        role = "holdout" if n == prob.holdout else "diagnosis"
        own = None if null_states is None else calibration
        why = failed if n not in states else None
        out[n] = ScanGap(n, role, before, after, rb, ra, calibration=own, failed=why)
    return out, states


def _admissible_interval(name: str, lower: float, upper: float) -> tuple[float, float]:
    """A parameter's interval cut to the values the model admits.

    The truth lies in :data:`calib.model.effects.ADMISSIBLE`, so the cut interval holds
    it exactly when the uncut one does: the coverage is unchanged. A saturated print
    (stiff inclusions) has a Wald interval reaching a negative stiffness ratio.

    Parameters
    ----------
    name : str
        A fit parameter's name (``theta``, an effect, a nuisance: those without an
        admissible range are returned as they are).
    lower, upper : float
        The interval, in the parameter's units.

    Returns
    -------
    (float, float)
        The cut interval; where it misses the admissible range entirely, the range's
        nearer end twice (an empty interval: the fit's value lies outside it).
    """
    a, b = ADMISSIBLE.get(name, (-np.inf, np.inf))
    lo, hi = min(max(float(lower), a), b), max(min(float(upper), b), a)
    return lo, hi


def _with_mesh_bound(theta: float, iv, prob: Problem) -> dict:
    """The refit's c1 interval with the model mesh's own error, and what it came from.

    The calibration's mesh check (GCI of ln c1 on its mesh) in quadrature with the noise,
    as ``calibrate`` does. On another mesh (a fallback size, ``--mesh-size``,
    ``--inclusion-mesh``) the check is not of this mesh (review W): its bound is carried
    to this mesh's element size by the check's order
    (:func:`calib.fitting.meshcheck.gci_at_size`), said in ``gci_from``.
    """
    check = (prob.work.record.get("uncertainty") or {}).get("mesh_check") or {}
    gci = None
    if not check:
        said = "none: the calibration ran no mesh check"
    elif check.get("gci_ln_c1") is None:
        said = "none: the calibration's mesh check failed"
    elif prob.own_mesh:
        gci, said = float(check["gci_ln_c1"]), "the calibration's mesh check on this mesh"
    elif not check.get("mesh_size_mm"):
        said = "none: the calibration's mesh check does not give its mesh size"
    else:
        gci = gci_at_size(check, prob.mesh_size_mm)
        said = _carried_said(check, prob)
    lo, hi = (float(np.hypot(theta - b, gci or 0.0)) for b in (iv.lower, iv.upper))
    return {
        "c1_ci95_pa": [float(np.exp(theta - lo)), float(np.exp(theta + hi))],
        "noise_only_c1_ci95_pa": [float(np.exp(iv.lower)), float(np.exp(iv.upper))],
        "gci_ln_c1": gci,
        "gci_from": said,
    }


def _carried_said(check: dict, prob: Problem) -> str:
    """Where a carried mesh bound came from, and what it does not see (``gci_from``)."""
    h, size = float(check["mesh_size_mm"]), prob.mesh_size_mm
    said = f"the calibration's mesh check on its {h:g} mm mesh"
    if size == h:
        said += ", on this other mesh of that size"
    else:
        said += f", carried to this {size:g} mm one by the check's order"
    sizes = [h, *(float(m["mesh_size_mm"]) for m in check.get("meshes") or ())]
    if not min(sizes) <= size <= max(sizes):  # review AR
        said += f" (extrapolated beyond the sizes checked, {min(sizes):g}-{max(sizes):g} mm)"
    record = prob.work.record
    curved = (record.get("reference_recovery") or {}).get("method") == "spatial"
    if curved or record.get("reference_state") == "prestress":
        # review AR: the check solved curved stress-free elements, this mesh straight ones
        said += "; checked with curved stress-free elements, where this mesh has straight ones"
    return said


def _intervals(fit: Refit, prob: Problem) -> dict:
    """95 % intervals of the final model's parameters (series estimator, calib.stats)."""
    f = fit.fields
    sample = sample_of(f, prob.points)
    r = f.stack(f.residual)
    # the interval of the refit's own estimate: like calibrate's fit, it takes no offset
    # per scan (review AV: the design held the offsets' columns, the interval of another
    # estimator, 4 % wider on the tiny skin twin; the refits' fitted offsets are 0.01 mm
    # there). The noise model is the tests' (per-scan constants cancel in a variogram)
    offsets = offset_columns(sample)
    r_c = r - offsets @ np.linalg.lstsq(offsets, r, rcond=None)[0]
    # one level even for scans imaged unlike: the refit is unweighted least squares, and
    # the series estimator takes each scan's scale from its residual (two scans of white
    # noise at 0.1 and 0.3 mm: the sandwich's standard error within 10 %)
    noise = session_noise(sample, r_c, max_lag_mm=NOISE_LAG_MM * prob.region_scale)
    try:
        alt = noise.alternatives
        ivs = parameter_intervals(fit.x, fit.jacobian(), r, sample, noise.best_arg,
                                  alternatives=alt)  # fmt: skip
    except ValueError as exc:
        return {"failed": str(exc)}
    out = {}
    for name, iv, v in zip(fit.names, ivs, fit.x, strict=False):
        entry = {"value": float(v), "ci95": [float(iv.lower), float(iv.upper)],
                 "standard_error": float(iv.standard_error)}  # fmt: skip
        lo, hi = _admissible_interval(name, iv.lower, iv.upper)
        if (lo, hi) != (iv.lower, iv.upper):  # e.g. a saturated print's Wald interval
            entry["ci95_unclipped"] = entry["ci95"]
            entry["ci95"] = [lo, hi]
        if name == "theta":
            entry.update(_with_mesh_bound(v, iv, prob))
        if name in PHYSICAL:  # the ratio - 1 of skin and inclusions, ln k of sliding
            q = PHYSICAL[name]
            entry[q.key] = float(q.convert(v))
            entry[q.ci_key] = [float(q.convert(b)) for b in entry["ci95"]]
        if name == "skin":  # (ratio - 1) x thickness: what the surface sees (review W)
            t = prob.skin_thickness_mm
            entry["excess_mm"] = float(v * t)
            entry["excess_ci95_mm"] = [float(b * t) for b in entry["ci95"]]
            entry["thickness_mm"] = float(t)
        out[name] = entry
    return out
