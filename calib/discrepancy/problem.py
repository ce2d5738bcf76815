"""The diagnosis problem: a calibrated work folder's model with the effect library added.

The model mesh is the calibration's own (``WORK/calibration/reference_mesh.vtu``'s
topology on the loaded reference geometry that ``calibrate`` saved with every state),
tagged by the volume fractions of a skin band and of the inclusions that ingest found
in the reference scan (:func:`calib.model.effects.tag_effect_regions`). At neutral
effect values it is exactly the calibration's model. Every solve goes through
:class:`calib.model.forward.ForwardModel` (stress-free recovery, warm starts).

Residuals are those of the calibration's ``surface`` objective: signed distances of the
measured surface points (the calibration's seeded subsample, off the back plate and
farther than the rim margin, :func:`rim_margin_of`, from it) to the
simulated surface, in the fiducial (reference) frame, on the curved surface
(:meth:`calib.model.residuals.SimulatedSurface.curved`: each facet carries its gap to the
reference scan's surface, which on coarse model meshes is as large as the rest of the
residual). Nuisance parameters act here:
a rigid offset per scan moves the measured points, a gravity error per scan turns the
load.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

import fem
from fem.units import DEFAULT_DENSITY_KG_M3, STANDARD_GRAVITY_M_S2

from ..data.work import WorkFolder, ingest_record
from ..fitting import CalibrationOptions
from ..model.effects import SKIN_THICKNESS_MM, EffectValues, tag_effect_regions
from ..model.forward import ForwardModel, ScanState
from ..model.reference import plate_height_mm, scan_height_mm
from ..model.residuals import Residuals, SimulatedSurface, scan_residuals
from ..stats.profile import HeightProfile

__all__ = [
    "RIM_MARGIN_MM",
    "DiagnosisError",
    "Nuisance",
    "Problem",
    "build_problem",
    "calibration_mesh_mm",
    "next_mesh_sizes",
    "parse_rim_margin",
    "plate_height_mm",
    "rim_margin_of",
    "rotate_gravity",
    "sliding_probe_pa_per_mm",
]

#: Measured points this near the back plate are not diagnosed by default (mm): there the
#: surface meets the clamped plate and the scan's surface extraction blurs the junction
#: over a few voxels. ``"element"`` leaves out one model element (:func:`rim_margin_of`).
RIM_MARGIN_MM = 5.0
#: Fewest fitted scans for leave-one-posture-out (:func:`calib.discrepancy.refit.lopo`),
#: without which no effect is named.
MIN_FITTED_SCANS = 2
#: The sliding probe's springs: this multiple of the tissue's own shear stiffness per area
#: of plate, ``2 c1 / H`` (:func:`sliding_probe_pa_per_mm`), so the plate slips by a
#: fraction of a millimetre and the response is in its linear range (0.5 mm in the
#: reference posture of the quick twin: 70 x 840 Pa / 74.5 mm = 790 Pa/mm, the probe 1000).
SLIDING_PROBE_TISSUE_MULTIPLE = 70.0
#: TetGen's bound on the largest dihedral angle (degrees) of the model meshes a diagnosis
#: tries last, where no mesh built as the calibration's admits a straight stress-free
#: reference: slivers at the clamped rim stop the inverse Newton, and on a twin 1.4 times
#: the usual size (c1 507 Pa) the 12 mm mesh recovers with this bound and stops at load
#: factor 0.96 without it (``fem.meshing``'s bound; the calibration's own, where it has one
#: as tight, is not retried).
STRAIGHT_RETRY_DIHEDRAL_DEG = 165.0

log = logging.getLogger(__name__)


class DiagnosisError(ValueError):
    """A work folder, scan choice or option the diagnosis cannot work with."""


@dataclass(frozen=True)
class Nuisance:
    """Nuisance values of one scan: gravity angles (rad) and a rigid offset (mm, rad).

    Attributes
    ----------
    gravity_rad : ndarray, shape (2,)
        Rotations of the scan's gravity direction about two axes normal to it.
    offset : ndarray, shape (6,)
        ``(t_x, t_y, t_z)`` in mm and ``(w_x, w_y, w_z)`` in rad, reference frame: the
        measured points move by ``t + w x (p - centre)``.
    """

    gravity_rad: np.ndarray = field(default_factory=lambda: np.zeros(2))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(6))


def gravity_axes(g: np.ndarray) -> np.ndarray:
    """Two unit axes normal to ``g`` (rows), a fixed choice for the gravity angles."""
    g = np.asarray(g, float) / np.linalg.norm(g)
    helper = np.eye(3)[int(np.argmin(np.abs(g)))]
    a = np.cross(g, helper)
    a /= np.linalg.norm(a)
    return np.array([a, np.cross(g, a)])


def rotate_gravity(g: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """``g`` turned by the rotation vector ``angles[0] a0 + angles[1] a1`` (Rodrigues)."""
    from scipy.spatial.transform import Rotation

    axes = gravity_axes(g)
    rot = Rotation.from_rotvec(np.asarray(angles_rad, float) @ axes)
    return rot.apply(np.asarray(g, float))


def _rigid(points: np.ndarray, offset: np.ndarray, centre: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    if not np.any(offset):
        return points
    R = Rotation.from_rotvec(offset[3:]).as_matrix()
    return (points - centre) @ R.T + centre + offset[:3]


@dataclass
class Problem:
    """The calibrated model of a work folder with the effect library, and its data.

    Attributes
    ----------
    work : WorkFolder
    fm : ForwardModel
        On the region-tagged loaded reference mesh, effects at their neutral values.
    base : EffectValues
        Neutral values (the calibration's nu and density).
    sim : SimulatedSurface
    points : dict of str to ndarray (k, 3)
        Measured surface points of each scan (reference frame, mm).
    centres : dict of str to ndarray (3,)
        Centroid of each scan's points (the rotation centre of its rigid offset).
    scans : list of str
        The diagnosis scans (fitted).
    holdout : str or None
        The held-out scan (never fitted).
    theta_calibrated : float
        ``ln c1`` of the calibration.
    inclusions : list of (ndarray, float)
        Inclusion centres (reference frame, mm) and diameters (mm).
    skin_thickness_mm : float
    mesh_note : str
        Empty on the calibration's model mesh; otherwise why the diagnosis runs on another
        one (a calibration with a prestressed reference: the effect fields need a
        straight stress-free mesh, found at the calibration's next mesh size).
    registration_tolerance_mm : dict of str to float
        How far a plausible rigid registration error moves a scan's points: three times
        its expected target registration error (ingest's ``tre_nipple_mm``,
        ``tre_tumour_mm``, Fitzpatrick's formula) plus half a voxel.
    rim_margin_mm : float
        Points nearer the back plate than this are not diagnosed (:func:`rim_margin_of`).
    mesh_size_mm : float
        Element size of the model mesh (mm): one element is the band at the clamped plate
        where the model's own discretisation error is largest (:func:`rim_margin_of`).
    rim_points : dict of str to ndarray (j, 3)
        Each scan's measured points within the rim margin: mapped by the localisation,
        never fitted nor tested.
    body_height_mm : float
        The reference scan's surface's greatest height above its back plate (mm); it sizes
        the sliding probe (:attr:`sliding_probe_pa_per_mm`). 0: not measured.
    profile : HeightProfile or None
        The residual's relative spread by height above the back plate (``--noise-profile
        plate``, :func:`calib.stats.height_profile`): every residual and its derivatives
        are divided by it (:meth:`residuals`), so the far band keeps its units (mm).
        None: a noise level the same at every height (the default).
    mesh_max_dihedral_deg : float or None
        TetGen's bound on the largest dihedral angle the model mesh was built with (the
        calibration's own mesh: the calibration's; None: TetGen's default).
    mesh_failed : list of (float, str)
        The model meshes tried before this one (size mm, why each failed); empty where the
        calibration's mesh or the size asked for is used as it is.
    discretisation : dict of str to ndarray (k,)
        Per diagnosis scan, the residual change from the model mesh to one
        :data:`calib.discrepancy.fields.COARSER_FACTOR` times coarser at the null fit's c1
        (mm; ``mesh_error="absorbed"``, :func:`calib.discrepancy.fields.discretisation_field`):
        the shape of the model mesh's own discretisation error, projected out of every
        test. Empty: not used (the default).
    imaging_noise_mm : dict of str to float
        Per diagnosis scan, its imaging's surface noise in relative terms
        (:func:`imaging_noise_mm`; scans without the ingest figures left out).
    """

    work: WorkFolder
    fm: ForwardModel
    base: EffectValues
    sim: SimulatedSurface
    points: dict
    centres: dict
    scans: list
    holdout: str | None
    theta_calibrated: float
    inclusions: list
    skin_thickness_mm: float
    registration_tolerance_mm: dict = field(default_factory=dict)
    mesh_note: str = ""
    rim_margin_mm: float = RIM_MARGIN_MM
    mesh_size_mm: float = 0.0
    rim_points: dict = field(default_factory=dict)
    body_height_mm: float = 0.0
    profile: HeightProfile | None = None
    mesh_max_dihedral_deg: float | None = None
    mesh_failed: list = field(default_factory=list)
    discretisation: dict = field(default_factory=dict)
    imaging_noise_mm: dict = field(default_factory=dict)

    @property
    def imaged_unlike(self) -> bool:
        """Whether the diagnosis scans' imaging noise differs (:data:`IMAGED_UNLIKE_RATIO`).

        The noise model then gives each scan its own level
        (:meth:`calib.stats.NoiseFit.scaled`); else one level for every scan.
        """
        v = [self.imaging_noise_mm[n] for n in self.scans if n in self.imaging_noise_mm]
        return len(v) > 1 and max(v) > IMAGED_UNLIKE_RATIO * min(v)

    @property
    def own_mesh(self) -> bool:
        """Whether the diagnosis' model mesh is the calibration's (its reference may not be).

        What the calibration measured of its mesh (the mesh check's GCI) holds for it.
        """
        return self.mesh.n_nodes == self.work.mesh.n_nodes

    @property
    def same_mesh(self) -> bool:
        """Whether the diagnosis runs on the calibration's model (mesh and reference).

        False where ``mesh_note`` says why not (another mesh, or a prestressed
        calibration diagnosed with a straight stress-free reference): the gap's before
        is then c1 alone solved on the diagnosis model, not the calibration's states.
        """
        return self.own_mesh and not self.mesh_note

    @property
    def region_scale(self) -> float:
        """The body's size relative to the twins' (1 where its height is not measured).

        :func:`calib.model.reference.body_scale` of :attr:`body_height_mm`: the
        factor on the localisation's radii and on the noise model's lags.
        """
        from ..model.reference import body_scale

        return body_scale(self.body_height_mm) if self.body_height_mm > 0 else 1.0

    @property
    def sliding_probe_pa_per_mm(self) -> float:
        """Tangential springs of the sliding screen's probe (Pa/mm).

        Sized by the calibrated c1 and :attr:`body_height_mm`
        (:func:`sliding_probe_pa_per_mm`); the sliding refit's bounds follow it
        (:func:`calib.discrepancy.refit.sliding_ln_k_bounds`).
        """
        return sliding_probe_pa_per_mm(float(np.exp(self.theta_calibrated)), self.body_height_mm)

    @property
    def nipple_node(self) -> int:
        """The nipple vertex of the diagnosis mesh."""
        return int(self.mesh.node_set("nipple")[0])

    @property
    def mesh(self) -> fem.TetMesh:
        """The loaded reference mesh with effect regions."""
        return self.fm.mesh

    def facet_gap_mm(self, *, max_points: int = 3000, seed: int = 0) -> dict | None:
        """How far the model mesh's straight facets lie from the reference scan's surface.

        The chord gap that :meth:`SimulatedSurface.curved` carries with the material,
        at the facet points nearest the reference scan's scored vertices beyond the rim
        margin (a seeded subsample of ``max_points``): the part of every residual that
        is the mesh's geometry, not its mechanics.

        Returns
        -------
        dict or None
            ``mean`` and ``sd`` (n - 1) of the signed gap (mm, negative inside the scanned
            surface) and ``n``; None where the surface carries no gap (straight facets)
            or no vertex lies beyond the margin.
        """
        ref = self.work.measurements.reference
        p = ref.surface_points(max_points=max_points, seed=seed)
        p = p[plate_height_mm(ref, p) >= self.rim_margin_mm]
        if self.sim.reference is None or len(p) < 2:
            return None
        gap = self.sim.gap_at(p)
        return {"mean": float(gap.mean()), "sd": float(gap.std(ddof=1)), "n": len(gap)}

    def measurement(self, name: str):
        """The :class:`ScanMeasurement` of a scan."""
        return self.work.measurements.scans[name]

    def gravity(self, name: str, nuisance: Nuisance | None = None) -> np.ndarray:
        """The scan's gravity direction (reference frame), turned by its nuisance angles."""
        g = self.measurement(name).gravity_ref
        if nuisance is None or not np.any(nuisance.gravity_rad):
            return g
        return rotate_gravity(g, nuisance.gravity_rad)

    def solve(
        self,
        theta: float,
        values: EffectValues,
        names: list[str],
        *,
        gradient: bool,
        nuisance: dict | None = None,
    ) -> dict[str, ScanState]:
        """Solve the postures of ``names`` at ``theta = ln c1`` with effect ``values``."""
        if self.fm.effects != values:
            self.fm.set_effects(values)
        nz = nuisance or {}
        gravities = {n: self.gravity(n, nz.get(n)) for n in names}
        return self.fm.evaluate(theta, gravities, gradient=gradient)

    def measured_points(
        self, name: str, nuisance: Nuisance | None = None, points_mm: np.ndarray | None = None
    ) -> np.ndarray:
        """The scan's points moved by its rigid offset.

        ``points_mm`` (e.g. its :attr:`rim_points`) instead of the diagnosed points move
        alike, about the diagnosed points' centre.
        """
        p = self.points[name] if points_mm is None else points_mm
        return p if nuisance is None else _rigid(p, nuisance.offset, self.centres[name])

    def residuals(
        self,
        name: str,
        positions_mm: np.ndarray,
        dpositions_mm: np.ndarray | None = None,
        nuisance: Nuisance | None = None,
        *,
        points_mm: np.ndarray | None = None,
    ) -> Residuals:
        """Surface residuals of one scan for simulated positions (and their derivative).

        At the scan's diagnosed points, or at ``points_mm`` (:meth:`measured_points`);
        divided by the :attr:`profile` at each point's height where there is one.
        """
        res = scan_residuals(
            "surface", self.measurement(name), self.mesh, self.sim, positions_mm,
            dpositions_mm, surface_points_mm=self.measured_points(name, nuisance, points_mm),
        )  # fmt: skip
        return self.weighted(name, res, self.points[name] if points_mm is None else points_mm)

    def weighted(self, name: str, res: Residuals, points_mm: np.ndarray) -> Residuals:
        """``res`` divided by the :attr:`profile` at the height of ``points_mm`` (unmoved).

        The weight of a point is that of its measured place: a rigid offset moves the
        point, not its weight. Without a profile, ``res`` itself.
        """
        if self.profile is None:
            return res
        w = self.profile.weights(plate_height_mm(self.measurement(name), points_mm))
        return Residuals(res.r * w, None if res.dr is None else res.dr * w, res.points_mm)


def _parameters(record: dict) -> dict:
    return (record.get("provenance") or {}).get("parameters") or {}


def _asked_mesh_mm(params: dict) -> float:
    """The model mesh size a calibration asked for (mm).

    Its ``mesh_size_mm``, else calibrate's default (:class:`calib.fitting.CalibrationOptions`).
    """
    return float(params.get("mesh_size_mm", CalibrationOptions.mesh_size_mm))


def calibration_mesh_mm(record: dict) -> float:
    """The element size of a calibration's own model mesh (mm), from its record.

    Parameters
    ----------
    record : dict
        A ``calibration.json``.

    Returns
    -------
    float
        The size of the mesh it ran on (``mesh.size_mm``), else the size asked for
        (``provenance.parameters.mesh_size_mm``, calibrate's default where absent).
    """
    return _ran_mesh_mm(record, _parameters(record))


def _ran_mesh_mm(record: dict, params: dict) -> float:
    """The size the calibration ran on (``mesh.size_mm``), else the one ``params`` ask for."""
    ran = (record.get("mesh") or {}).get("size_mm")
    return float(ran) if ran else _asked_mesh_mm(params)


def _own_bound(work: WorkFolder) -> float | None:
    """TetGen's dihedral bound the calibration meshed with (None: TetGen's default)."""
    return _parameters(work.record).get("mesh_max_dihedral_deg")


def _recovered_model(
    work: WorkFolder, model_on, size_mm: float, spheres=None, *, bound: float | None = None
):
    """The model on the reference scan's mesh of ``size_mm``, recovered at the calibrated c1.

    ``model_on(loaded_mesh)`` builds the model (it tags the effect regions); the recovery
    stays cached for the null fit. The mesh is meshed as the calibration's was (its
    TetGen bound on the largest dihedral angle, ``mesh_max_dihedral_deg``); ``spheres``,
    ``(inclusions, element size mm)``, are meshed inside it. ``bound``, when given,
    replaces the calibration's dihedral bound. Raises ``fem.ConvergenceError`` where it
    fails.
    """
    from ..model.reference import reference_mesh

    if bound is None:
        bound = _own_bound(work)
    inner = {} if spheres is None else {"spheres": spheres[0], "sphere_size_mm": spheres[1]}
    loaded = reference_mesh(
        work.measurements.reference, size_mm=size_mm, max_dihedral_deg=bound, **inner
    )
    fm = model_on(loaded)
    fm.stress_free(float(np.log(work.record["c1_pa"])))
    return fm


def _first_recovered(
    work: WorkFolder,
    model_on,
    sizes: Sequence[float],
    spheres=None,
    *,
    bound: float | None = None,
    say=None,
):
    """The model on the first of ``sizes`` whose recovery at the calibrated c1 succeeds.

    Each size is built by :func:`_recovered_model`. Returns the model and its size (both
    None where every size failed) and the sizes that failed before it, each with its
    ``fem.ConvergenceError``. A mesh that cannot be built is a :class:`DiagnosisError`
    naming it, except with a ``bound`` of the diagnosis' own (a last try): there it is
    one more failed size. ``say`` (progress lines) is told of each size before it is
    tried: on a large body a try takes minutes.
    """
    say = say or log.info
    failed = []
    for s in sizes:
        with_bound = "" if bound is None else f" with a {bound:g} deg dihedral bound"
        mesh = f"a {s:g} mm model mesh{_spheres_said(spheres)}{with_bound}"
        say(f"  recovering a straight stress-free reference at the calibrated c1 on {mesh}")
        try:
            return _recovered_model(work, model_on, s, spheres, bound=bound), s, failed
        except fem.MeshError as exc:
            if bound is not None:
                failed.append((s, f"TetGen built no mesh: {exc}"))
                continue
            raise DiagnosisError(
                f"{work.path}: no {s:g} mm model mesh{_spheres_said(spheres)}: {exc}"
            ) from exc
        except fem.ConvergenceError as exc:
            failed.append((s, exc))
    return None, None, failed


def _spheres_said(spheres) -> str:
    """How a model mesh meshes ``spheres`` ``(inclusions, element size mm)``, for notes."""
    if spheres is None:
        return ""
    from ..model.reference import meshed_spheres

    n, h = len(meshed_spheres(*spheres)), spheres[1]
    them = "inclusion" if n == 1 else "inclusions"
    return f" with its {n} {them} {h:g} mm or wider meshed as spheres of {h:g} mm"


class _ModelMesh(NamedTuple):
    """The diagnosis' model and how its mesh was chosen (:func:`build_problem`)."""

    fm: ForwardModel
    note: str  # why the mesh is not the calibration's as it was ("" where it is)
    size_mm: float
    max_dihedral_deg: float | None  # TetGen's bound it was built with (None: TetGen's default)
    failed: list  # (size mm, why) of each mesh tried before it


def _failures(failed: list, bound: float | None = None) -> list:
    """``(size mm, why)`` of each failed try, for the refit's record."""
    with_bound = "" if bound is None else f"with a {bound:g} deg dihedral bound: "
    return [(float(t), f"{with_bound}{exc}") for t, exc in failed]


def _sized_model(
    work: WorkFolder,
    params: dict,
    model_on,
    size_mm: float,
    spheres=None,
    *,
    then: Sequence[float] = (),
    say=None,
):
    """The model on a mesh of ``size_mm`` (asked for), its stress-free reference recovered.

    Built from the reference scan as the calibration builds its own
    (:func:`_recovered_model`), with ``spheres`` ``(inclusions, element size mm)`` meshed
    inside. Where the recovery at the calibrated c1 fails on ``size_mm``, the sizes
    ``then`` are tried in turn (empty: a size asked for is not replaced), and where all
    fail, the same sizes again with TetGen's dihedral bound
    :data:`STRAIGHT_RETRY_DIHEDRAL_DEG` (unless the calibration's is as tight); the note
    says why the diagnosis runs on another mesh. Returns a :class:`_ModelMesh` whose note says
    the diagnosis mesh is not the calibration's.
    """
    inner, own = _spheres_said(spheres), _ran_mesh_mm(work.record, params)
    bound = used = _own_bound(work)
    sizes = [size_mm, *then]
    fm, s, failed = _first_recovered(work, model_on, sizes, spheres, say=say)
    if fm is None and (bound is None or bound > STRAIGHT_RETRY_DIHEDRAL_DEG):
        # the same sizes with fewer slivers (a 1.4x twin's 12 mm mesh, a twin's 9 mm one)
        used = STRAIGHT_RETRY_DIHEDRAL_DEG
        fm, s, bounded = _first_recovered(work, model_on, sizes, spheres, bound=used, say=say)
        failed = failed + _failures(bounded, used)
    if fm is None:
        raise DiagnosisError(
            f"{work.path}: no straight stress-free reference on a {_tried(failed, inner)}; "
            "choose another --mesh-size"
        )
    if not failed:
        note = f"diagnosed on a {s:g} mm mesh{inner}, as asked (the calibration's: {own:g} mm)"
        return _ModelMesh(fm, note, s, bound, [])
    with_bound = "" if used == bound else f" with TetGen's dihedral bound {used:g} deg"
    note = (
        f"no straight stress-free reference on a {_tried(failed, inner)}; diagnosed on "
        f"the {s:g} mm mesh{inner}{with_bound} (the calibration's: {own:g} mm)"
    )
    return _ModelMesh(fm, note, s, used, _failures(failed))


def _tried(failed: list, inner: str) -> str:
    """The model meshes whose recovery at the calibrated c1 failed, each with why."""
    (s, exc), rest = failed[0], failed[1:]
    said = f"{s:g} mm model mesh{inner} at the calibrated c1 ({exc})"
    return said + "".join(f" nor on a {t:g} mm one ({e})" for t, e in rest)


def next_mesh_sizes(params: dict, *, ran_mm: float | None = None) -> list[float]:
    """The model mesh sizes a diagnosis tries after the calibration's own (mm).

    The calibration's retry sizes (``mesh_retry_mm``) other than the size it asked for,
    else that size + 2 and + 4 mm; the size it ran on (``ran_mm``) left out.

    Parameters
    ----------
    params : dict
        The calibration's parameters (``calibration.json``'s ``provenance.parameters``).
    ran_mm : float, optional
        The size the calibration ran on (:func:`calibration_mesh_mm`), where it fell back
        to a retry size.

    Returns
    -------
    list of float
    """
    size = _asked_mesh_mm(params)
    sizes = [float(s) for s in params.get("mesh_retry_mm") or () if float(s) != size]
    return [s for s in sizes or [size + 2.0, size + 4.0] if s != ran_mm]


def _straight_model(
    work: WorkFolder,
    params: dict,
    model_on,
    *,
    own_size: bool,
    why: str = "its reference is prestressed",
    say=None,
):
    """A model of the reference scan whose stress-free reference has straight elements.

    The calibration's reference is the prestressed loaded mesh (its mesh admits no
    straight stress-free elements, :mod:`calib.model.forward`); the effect fields
    differentiate through a straight stress-free recovery, so the diagnosis takes the
    calibration's next mesh sizes (``mesh_retry_mm``, else +2 and +4 mm; its own size
    first with ``own_size``) and the first whose recovery at the calibrated c1 succeeds
    (``model_on(loaded_mesh)`` builds the model; its recovery stays cached for the null
    fit). The calibration's own mesh is skipped also when a straight recovery at the
    calibrated c1 fails there (``why`` says which). Where every one fails, the same
    sizes, the calibration's own first, are meshed again with TetGen's dihedral bound
    :data:`STRAIGHT_RETRY_DIHEDRAL_DEG` (fewer slivers), unless the calibration's bound
    is as tight. The calibration's own size is the one it ran on (a calibration that
    fell back to a retry size ran there). Returns a :class:`_ModelMesh`.
    """
    size = _ran_mesh_mm(work.record, params)
    others = next_mesh_sizes(params, ran_mm=size)
    fm, s, failed = _first_recovered(work, model_on, ([size] if own_size else []) + others, say=say)
    own_bound = _own_bound(work)
    if fm is None and (own_bound is None or own_bound > STRAIGHT_RETRY_DIHEDRAL_DEG):
        bound = STRAIGHT_RETRY_DIHEDRAL_DEG
        again = [size, *others]
        fm, s, failed_bound = _first_recovered(work, model_on, again, bound=bound, say=say)
        if fm is not None:
            tried = "; ".join(f"{t:g} mm: {exc}" for t, exc in failed)
            tried = f" nor on others meshed as it was ({tried})" if failed else ""
            bounded = "".join(f"; with the bound, {t:g} mm: {exc}" for t, exc in failed_bound)
            said = "none" if own_bound is None else f"{own_bound:g} deg"
            note = (
                f"no straight stress-free reference on the calibration's mesh ({why}){tried}"
                f"{bounded}; diagnosed on the {s:g} mm mesh with TetGen's dihedral bound "
                f"{bound:g} deg (the calibration's: {said})"
            )
            return _ModelMesh(
                fm, note, s, bound, _failures(failed) + _failures(failed_bound, bound)
            )
        failed += _failures(failed_bound, bound)
    if fm is None:
        tried = "; ".join(f"{t:g} mm: {exc}" for t, exc in failed)
        tried = f"nor on other meshes ({tried})" if failed else "and no other size to try"
        raise DiagnosisError(
            f"{work.path}: no straight stress-free reference on the calibration's mesh ({why}) "
            f"{tried}; recalibrate with another --mesh-size"
        )
    if s == size:  # the calibration's mesh size, rebuilt from the same scan
        note = (
            f"the calibration's reference is prestressed (curved stress-free elements); "
            f"diagnosed with a straight stress-free reference on its own {s:g} mm mesh"
        )
        return _ModelMesh(fm, note, s, own_bound, [])
    note = (
        f"the calibration's {size:g} mm mesh admits no straight stress-free reference "
        f"({why}); diagnosed on the {s:g} mm mesh"
    )
    return _ModelMesh(fm, note, s, own_bound, _failures(failed))


def _loaded_nodes(work: WorkFolder) -> np.ndarray:
    """The loaded reference geometry of the model mesh, from the saved states."""
    refs = [s.reference_positions_mm for s in work.states.values()]
    refs = [r for r in refs if r is not None]
    if not refs:
        raise DiagnosisError(
            f"{work.path}: no saved state with displacement_from_reference_mm (run "
            "`phantom-calib calibrate` again)"
        )
    spread = max(float(np.abs(r - refs[0]).max()) for r in refs)
    if spread > 1e-6:
        raise DiagnosisError(f"{work.path}: the saved states disagree on the reference geometry "
                             f"by {spread:.3g} mm")  # fmt: skip
    return refs[0]


def reference_inclusions(work: WorkFolder) -> list[tuple[np.ndarray, float]]:
    """Inclusions ingest detected in the reference scan: (centre mm, diameter mm), ref frame.

    The ``inclusions`` effect tags these, all at one stiffness ratio; regions of inclusion
    contrast larger than ingest accepts (:func:`inclusions_left_out`) are said.
    """
    ref = work.measurements.reference
    doc = ingest_record(work, ref.name)
    if left := _too_large(doc):
        log.warning(
            "reference scan %r: ingest left out %d region(s) of inclusion contrast too large "
            "for an inclusion (ingest.json quality.inclusions_too_large): the inclusions "
            "effect tags only the %d it found",
            ref.name,
            left,
            len(doc.get("inclusions") or []),
        )
    T = ref.T_ref_from_scan
    out = []
    for inc in doc.get("inclusions") or []:
        c = np.asarray(inc["centre_lps_mm"], float)
        out.append((T[:3, :3] @ c + T[:3, 3], float(inc["diameter_mm"])))
    return out


def inclusions_left_out(work: WorkFolder) -> int:
    """Regions of inclusion contrast too large for ingest in the reference scan.

    0 where an older ingest did not count them (``quality.inclusions_too_large``).
    """
    return _too_large(ingest_record(work, work.measurements.reference.name))


def _too_large(doc: dict) -> int:
    return int((doc.get("quality") or {}).get("inclusions_too_large") or 0)


def _registration_tolerance(work: WorkFolder, name: str) -> float:
    """3 x the scan's expected TRE (ingest.json) + half its largest voxel edge, mm.

    The largest edge: on thick slices a surface point is placed to half a slice along
    the slice axis.
    """
    doc = ingest_record(work, name)
    tre = max(float(doc.get("tre_nipple_mm") or 0.0), float(doc.get("tre_tumour_mm") or 0.0))
    voxel = max(doc.get("voxel_size_mm") or [1.0])
    return 3.0 * tre + 0.5 * float(voxel)


#: The diagnosis scans are imaged unlike where one's :func:`imaging_noise_mm` is more than
#: this many times another's. The quick twins' scans, rendered alike: 1.06 at most (image
#: noise 0.032-0.034 of the body level for the renderer's 1/30, 1.5 mm voxels; 1.13
#: before ingest revision 6, when the markers' squares joined the background's).
IMAGED_UNLIKE_RATIO = 1.5


def imaging_noise_mm(work: WorkFolder, name: str) -> float | None:
    """A scan's surface noise from its imaging alone: voxel size times image noise (mm).

    The root mean square of the voxel edges (a voxel's extent along a surface normal in
    no particular direction) times the image noise relative to the body level
    (ingest.json ``voxel_size_mm``, ``quality.seg_noise_sigma_rel``): a surface placed by
    a partial-volume edge moves by about the noise over the edge's slope, the body level
    over a voxel. The quick twin in 4 mm slices against 1.5 mm voxels: an rms edge 1.74
    times longer at the same image noise (the renderer's SNR of 30), and a calibration
    residual's sd 2 times larger (0.53 against 0.26 mm: ``benchmarks/bench_slices.py``).
    A relative measure, for comparing the scans of one session, and independent of the
    model (a residual's own short-lag spread is not: :func:`calib.stats.noise.session_noise`).
    None without those figures.
    """
    return _imaging_noise(ingest_record(work, name))


def _imaging_noise(doc: dict) -> float | None:
    """:func:`imaging_noise_mm` of an ingest record."""
    voxel = doc.get("voxel_size_mm")
    noise = (doc.get("quality") or {}).get("seg_noise_sigma_rel")
    if not voxel or noise is None or not np.isfinite(noise) or noise <= 0:
        return None
    return float(np.sqrt(np.mean(np.square(np.asarray(voxel, float)))) * noise)


def comparable_imaging_noise(work: WorkFolder, scans) -> dict[str, float]:
    """:func:`imaging_noise_mm` of the scans, where their image noise was measured alike.

    Ingest reads the noise from a Rayleigh background or, where there is none, from the
    body's interior (``quality.seg_noise_method``), and the two may disagree on correlated
    noise (interpolated images: the interior's reading at the lag where they decorrelate
    is 0.93-1.0 of the truth; at lag 1 it was 0.47-0.86, review AF):
    where the scans' noise was measured in different ways, their image noise is not
    compared, only their voxels (each scan's voxel edge times the scans' median image
    noise, with a warning; review AH: returning none lost a 4 mm scan's 1.74 times).
    ``background`` and ``background (offset)`` are one way.
    """
    docs = {n: ingest_record(work, n) for n in scans}  # each record read once
    values = {n: v for n, doc in docs.items() if (v := _imaging_noise(doc)) is not None}
    quality = {n: docs[n].get("quality") or {} for n in values}
    methods = {n: quality[n].get("seg_noise_method", "background") for n in values}
    if len({m.split(" ")[0] for m in methods.values()}) > 1:
        log.warning(
            "%s: the scans' image noise was measured in different ways (%s: ingest.json "
            "quality.seg_noise_method); only their voxel sizes are compared",
            work.path,
            ", ".join(f"{n} {m}" for n, m in methods.items()),
        )
        noise = {n: float(quality[n]["seg_noise_sigma_rel"]) for n in values}
        common = float(np.median(list(noise.values())))
        return {n: v / noise[n] * common for n, v in values.items()}
    return values


def failed_scans(work: WorkFolder) -> dict[str, str]:
    """The calibration's scans with no FE solution at its c1, with the reason (by name)."""
    scans = work.record["scans"].items()
    return {n: str(s.get("failed")) for n, s in scans if s.get("failed")}


def choose_scans(work: WorkFolder, holdout: str | None) -> tuple[list[str], str | None]:
    """The diagnosis scans and the held-out one.

    ``holdout=None`` holds out the first validation scan of the calibration (session
    order), if any, where that leaves :data:`MIN_FITTED_SCANS` scans to fit (else
    nothing, with a warning); ``"none"`` holds out nothing. Every other scan but the
    reference is fitted. Naming an effect needs leave-one-posture-out over at least two
    fitted scans: a named holdout that leaves fewer is refused, and a session with a
    single scan to fit is warned about (nothing can be named). Scans whose calibrated
    state failed (:func:`failed_scans`) are left out, with a warning.
    """
    failed = failed_scans(work)
    if failed:
        log.warning(
            "%s: left out of the diagnosis, no FE solution at the calibrated c1: %s",
            work.path,
            "; ".join(f"{n} ({why})" for n, why in failed.items()),
        )
    names = [n for n in work.record["scans"] if n not in failed]
    roles = {n: work.record["scans"][n]["role"] for n in names}
    named = holdout is not None and holdout.lower() != "none"
    if holdout is None:
        holdout = next((n for n in names if roles[n] == "validation"), None)
        if holdout is not None and len(names) - 1 < MIN_FITTED_SCANS:
            msg = "%s: holding out %s would leave %d scan(s) to fit, and naming an effect "
            msg += "needs leave-one-posture-out over %d: nothing is held out"
            log.warning(msg, work.path, holdout, len(names) - 1, MIN_FITTED_SCANS)
            holdout = None
    elif holdout.lower() == "none":
        holdout = None
    elif holdout not in names:
        raise DiagnosisError(
            f"holdout (--holdout) {holdout!r}: not a scan with a calibrated state; choose "
            f"from {names}"
        )
    scans = [n for n in names if n != holdout]
    if not scans:
        raise DiagnosisError(f"{work.path}: no scan left to diagnose besides the held-out one")
    if named and len(scans) < MIN_FITTED_SCANS:
        raise DiagnosisError(
            f"holdout (--holdout) {holdout}: leaves {scans} to fit, and naming an effect "
            f"needs leave-one-posture-out over {MIN_FITTED_SCANS} scans (holdout 'none', "
            "--holdout none, fits all)"
        )
    if len(scans) < MIN_FITTED_SCANS:
        msg = "%s: a single scan to fit (%s): leave-one-posture-out cannot run, so no effect "
        log.warning(msg + "can be named (the screen and maps are still made)", work.path, scans[0])
    return scans, holdout


def rim_margin_of(mesh_size_mm: float, margin: float | Literal["element"] = RIM_MARGIN_MM) -> float:
    """The band at the back plate that the diagnosis leaves out (mm).

    Parameters
    ----------
    mesh_size_mm : float
        Size of the diagnosis's model mesh.
    margin : float or "element"
        A width in mm, taken as it is, or ``"element"``: one model element,
        ``max(RIM_MARGIN_MM, mesh_size_mm)``. The clamped edge is a stress singularity
        that the first layer of elements cannot resolve, and a homogeneous model against
        a homogeneous truth leaves a misfit there that no library effect explains. On
        the quick twin's null sets (14-18 mm model meshes) the residual's rms by height
        above the plate is 0.19-0.56 mm within 5 mm, 0.13-0.61 mm at 5-12 mm, 0.10-0.44
        mm at 12-16 mm, 0.10-0.25 mm at 16-20 mm and 0.06-0.14 mm beyond 30 mm
        (``python benchmarks/bench_diagnose.py --out DIR --rim-profile``). Leaving one
        element out lets a stiff inclusion explain half of what remains, but it also
        sharpens the noise model, so per-scan nuisances screen significant more often
        (``docs/diagnose-evidence.md``, "A rim margin of one element"): it is an option,
        not the default. The share a
        named effect must explain is judged beyond one element by default, with the
        tests on every diagnosed point (``DiagnosisOptions.explained_margin_mm``).

    Returns
    -------
    float
    """
    if margin == "element":
        return max(RIM_MARGIN_MM, float(mesh_size_mm))
    if isinstance(margin, str):
        raise DiagnosisError(f"rim margin must be a width in mm or 'element', got {margin!r}")
    return float(margin)


def parse_rim_margin(text: str, flag: str = "--rim-margin") -> float | Literal["element"]:
    """A margin at the plate as typed (``flag``): a width in mm or ``element``."""
    if text.strip() == "element":
        return "element"
    try:
        return float(text)
    except ValueError:
        raise DiagnosisError(f"{flag} must be a width in mm or 'element', got {text!r}") from None


def sliding_probe_pa_per_mm(c1_pa: float, height_mm: float) -> float:
    """Tangential spring stiffness of the sliding probe for a body (Pa/mm).

    :data:`SLIDING_PROBE_TISSUE_MULTIPLE` times the tissue's own shear stiffness per area
    of plate, ``2 c1 / H`` (initial shear modulus over the body's height above the
    plate), rounded to the nearest power of ten: the probe needs the right order of
    magnitude only, and a rounded one keeps its amplitude's unit the same for bodies
    alike (the twins' 750-1200 Pa/mm all give 1000).

    Parameters
    ----------
    c1_pa : float
        The calibrated c1 (Pa).
    height_mm : float
        The body's height above the back plate (mm).

    Returns
    -------
    float
        A power of ten, Pa/mm.
    """
    if not (np.isfinite(c1_pa) and np.isfinite(height_mm) and c1_pa > 0 and height_mm > 0):
        raise DiagnosisError(
            f"the sliding probe needs a positive c1 and body height, got c1 {c1_pa!r} Pa "
            f"and height {height_mm!r} mm"
        )
    tissue = 2.0 * float(c1_pa) / float(height_mm)
    return float(10.0 ** round(np.log10(SLIDING_PROBE_TISSUE_MULTIPLE * tissue)))


#: A scan's slice thickness across the plate (``back_plane.voxel_depth_mm``) plus this
#: (mm) beyond the rim margin, the margin is said to be narrow for it: the terraced,
#: partial-volume junction with the plate reaches past it (review W).
RIM_BLUR_MM = 1.5


def _say_coarse(where, size_mm: float, height_mm: float) -> bool:
    """Warn where a model mesh leaves the body few elements tall; whether it did.

    :data:`calib.model.reference.MIN_ELEMENTS_IN_HEIGHT`, as ``calibrate`` says of its
    own mesh (review W: a fallback size of the diagnosis was not said).
    """
    from ..model.reference import MIN_ELEMENTS_IN_HEIGHT

    if height_mm >= MIN_ELEMENTS_IN_HEIGHT * size_mm:
        return False
    log.warning(
        "%s: the diagnosis' model mesh of %g mm leaves the %.0f mm tall body %.1f elements "
        "tall, fewer than %g; --mesh-size %.0f is about as fine as the twins'",
        where,
        size_mm,
        height_mm,
        height_mm / size_mm,
        MIN_ELEMENTS_IN_HEIGHT,
        height_mm / 6.0,
    )
    return True


def _off_the_rim(scan, n_pts: int, seed: int, margin_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The calibration's seeded surface points of a scan: beyond the rim margin, within it.

    A margin narrower than the scan's slice thickness across the plate plus
    :data:`RIM_BLUR_MM` is warned about (the blurred junction is then diagnosed).
    """
    p = scan.surface_points(max_points=n_pts, seed=seed)
    depth = getattr(scan, "back_voxel_depth_mm", None)
    if depth is not None and 0 < margin_mm < depth + RIM_BLUR_MM:
        log.warning(
            "%s: its slices are %.1f mm thick across the back plate, and the rim margin "
            "(%g mm) leaves part of its blurred junction with the plate in the diagnosis; "
            "--rim-margin %.0f leaves it out",
            scan.name,
            depth,
            margin_mm,
            np.ceil(depth + RIM_BLUR_MM),
        )
    if margin_mm <= 0:
        return p, p[:0]
    keep = plate_height_mm(scan, p) >= margin_mm
    if keep.sum() < 0.5 * len(p):
        raise DiagnosisError(
            f"{scan.name}: only {int(keep.sum())} of {len(p)} surface points lie farther "
            f"than the rim margin ({margin_mm:g} mm) from the back plate; lower it "
            "(--rim-margin)"
        )
    return p[keep], p[~keep]


def build_problem(
    work: WorkFolder,
    *,
    holdout: str | None = None,
    skin_thickness_mm: float = SKIN_THICKNESS_MM,
    max_points: int | None = None,
    rim_margin_mm: float | Literal["element"] = RIM_MARGIN_MM,
    mesh_size_mm: float | None = None,
    inclusion_mesh_mm: float | None = None,
    say=None,
) -> Problem:
    """The diagnosis problem of a calibrated work folder, its stress-free reference recovered.

    Parameters
    ----------
    work : WorkFolder
        :func:`calib.data.read_work`.
    holdout : str, optional
        See :func:`choose_scans`.
    skin_thickness_mm : float
        Band of the skin effect.
    max_points : int, optional
        Points per scan; default the calibration's.
    rim_margin_mm : float or "element"
        Measured points nearer than this to the scan's back plate are left out (mm;
        ``"element"``: one model element, :func:`rim_margin_of`); 0 keeps them all.
    mesh_size_mm : float, optional
        A model mesh of this size (mm), built from the reference scan, instead of the
        calibration's; its stress-free reference is recovered at the calibrated c1.
    inclusion_mesh_mm : float, optional
        A model mesh built from the reference scan (of ``mesh_size_mm``, else the
        calibration's size) with the segmented inclusions meshed as spheres of elements
        of this size (:func:`calib.model.reference.reference_mesh`); its stress-free
        reference is recovered at the calibrated c1. Without ``mesh_size_mm``, where that
        recovery fails on the calibration's size, the next sizes
        (:func:`next_mesh_sizes`) are tried, then the same sizes again with TetGen's
        dihedral bound :data:`STRAIGHT_RETRY_DIHEDRAL_DEG`, and the mesh note says so; a
        size asked for is never replaced (it is meshed again with the bound).
    say : callable, optional
        Progress lines (default: the log at INFO): each model mesh tried, where the
        calibration's own is not used as it is.

    Raises
    ------
    DiagnosisError
        Among others: a diagnosis' own refit (its effects would be read as c1 alone),
        ``inclusion_mesh_mm`` without inclusions segmented in the reference scan, or with
        one that cannot be meshed as a sphere inside the body.
    """
    record = work.record
    model = record["model"]
    if record.get("diagnosis") or model.get("effects"):
        made = record.get("diagnosis") or {}
        raise DiagnosisError(
            f"{work.path}: the refitted model of a diagnosis (named: "
            f"{', '.join(made.get('named') or []) or 'none'}); diagnose the calibration it came "
            f"from ({made.get('source_work', 'its source work folder')})"
        )
    params = _parameters(record)
    state = record.get("reference_state", "unload")
    if state not in ("unload", "prestress", "shortcut"):
        raise DiagnosisError(
            f"{work.path}: reference_state {state!r} is not one of unload, prestress, shortcut"
        )
    scans, held = choose_scans(work, holdout)
    nu = float(model.get("nu", 0.499))
    density = float(model.get("density_kg_m3", DEFAULT_DENSITY_KG_M3))
    inclusions = reference_inclusions(work)
    base = EffectValues(nu=nu, density_kg_m3=density)
    prestressed = (
        state == "prestress" or (record.get("reference_recovery") or {}).get("method") == "spatial"
    )
    state = "unload" if prestressed else state  # the effect fields need straight elements

    def model_on(loaded: fem.TetMesh) -> ForwardModel:
        """The region-tagged model of a loaded reference mesh, effects neutral."""
        mesh = tag_effect_regions(
            loaded, skin_thickness_mm=skin_thickness_mm, inclusions=inclusions
        )
        return ForwardModel(
            mesh, work.measurements.reference.gravity_ref, nu=nu, density_kg_m3=density,
            reference_state=state,
            formulation=model.get("formulation", "taylor-hood"),
            g_m_s2=float(model.get("g_m_s2") or STANDARD_GRAVITY_M_S2),
            fixed_point_fallback=False, effects=base,
        )  # fmt: skip

    if inclusion_mesh_mm is not None:
        if not inclusions:
            raise DiagnosisError(
                f"{work.path}: inclusion_mesh_mm={inclusion_mesh_mm:g} asks for the inclusions "
                "to be meshed, but ingest segmented none in the reference scan"
            )
        size = calibration_mesh_mm(record) if mesh_size_mm is None else mesh_size_mm
        # a size asked for stays; the calibration's (the one it ran on) gives way to its
        # next sizes
        then = next_mesh_sizes(params, ran_mm=size) if mesh_size_mm is None else []
        spheres = (inclusions, inclusion_mesh_mm)
        chosen = _sized_model(work, params, model_on, size, spheres, then=then, say=say)
    elif mesh_size_mm is not None:
        chosen = _sized_model(work, params, model_on, mesh_size_mm, say=say)
    elif prestressed:
        # --reference-state prestress: its own mesh may admit one; a switched unload: not
        own = record.get("reference_state") == "prestress"
        chosen = _straight_model(work, params, model_on, own_size=own, say=say)
    else:
        fm = model_on(work.mesh.with_nodes(_loaded_nodes(work)))
        chosen = _ModelMesh(fm, "", calibration_mesh_mm(record), _own_bound(work), [])
        try:
            fm.stress_free(float(np.log(record["c1_pa"])))
        except fem.ConvergenceError as exc:
            # a cold recovery can fail where the calibration's own did not (see the README)
            why = f"its recovery fails at the calibrated c1: {exc}"
            chosen = _straight_model(work, params, model_on, own_size=False, why=why, say=say)
    fm, note, size = chosen.fm, chosen.note, chosen.size_mm
    margin = rim_margin_of(size, rim_margin_mm)
    mesh = fm.mesh
    n_pts = int(max_points or params.get("max_points", 3000))
    seed = int(params.get("seed", 0))
    split = {
        n: _off_the_rim(work.measurements.scans[n], n_pts, seed, margin)
        for n in [*scans, *([held] if held else [])]
    }
    points = {n: beyond for n, (beyond, _) in split.items()}
    centres = {n: p.mean(axis=0) for n, p in points.items()}
    ref = work.measurements.reference  # facets carry their gap to the scanned surface
    sim = SimulatedSurface.of(mesh).curved(mesh.nodes_mm, ref.vertices_mm, ref.faces)
    tolerance = {n: _registration_tolerance(work, n) for n in points}
    imaging = comparable_imaging_noise(work, scans)
    height = scan_height_mm(ref)  # as calibrate's noise model and the remesh take it
    if size != calibration_mesh_mm(record):  # calibrate said so of its own size
        _say_coarse(work.path, size, height)
    return Problem(
        work=work, fm=fm, base=base, sim=sim, points=points,
        centres=centres, scans=scans, holdout=held,
        theta_calibrated=float(np.log(record["c1_pa"])), inclusions=inclusions,
        skin_thickness_mm=float(skin_thickness_mm), registration_tolerance_mm=tolerance,
        mesh_note=note, rim_margin_mm=margin, mesh_size_mm=float(size),
        rim_points={n: within for n, (_, within) in split.items()},
        body_height_mm=height,
        mesh_max_dihedral_deg=None if chosen.max_dihedral_deg is None
        else float(chosen.max_dihedral_deg),
        mesh_failed=chosen.failed, imaging_noise_mm=imaging,
    )  # fmt: skip
