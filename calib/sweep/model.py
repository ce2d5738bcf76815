"""The calibrated model of a work folder, as a sweep's workers need it.

Reads ``WORK/calibration.json`` (its ``model`` block and ``c1_pa``) and the stress-free
reference mesh ``WORK/calibration/reference_mesh.vtu`` (node sets ``set:back``,
``set:surface``, ``set:nipple`` as point data), checking that both are from the same run
(:func:`calib.io.check_run`). The result, :class:`SweepModel`, is a small picklable value
(arrays and numbers) that every worker turns into the same FE model.

A calibration whose reference is the prestressed loaded mesh (``reference_recovery.method``
``spatial``: curved stress-free elements, :mod:`fem.prestress`) is swept on that loaded
mesh (``model.prestress``: ``calibration/loaded_reference_mesh.vtu``) with its prestress,
rebuilt on each worker from the saved inverse state
(``calibration/reference_prestress.npz``); stored displacements are then relative to the
loaded mesh, whose nodes are the store's ``mesh/nodes_mm``.

A diagnosis' refitted model (``WORK/diagnosis/refit``, ``model.effects`` naming effects
of the library: a skin, stiffer inclusions, c2, nu, the plate on springs) is swept with
them: the mesh's effect regions and :func:`calib.model.effects.effect_model`.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "CalibrationMissingError",
    "SweepModel",
    "UnsupportedReferenceError",
    "load_sweep_model",
    "mesh_sha256",
]

_REQUIRED = (
    "nu",
    "density_kg_m3",
    "formulation",
    "support",
    "g_m_s2",
    "nipple_node",
    "R_ref_from_phantom",
    "reference_mesh",
)
_SUPPORTS = ("clamped", "sliding")
_NEO_HOOKEAN = "neo-hookean (uncoupled), W = c1 (I1bar - 3) + U(J)"


class CalibrationMissingError(FileNotFoundError):
    """The work folder holds no (complete) calibration to sweep."""


class UnsupportedReferenceError(ValueError):
    """The calibration's reference state cannot be swept (its prestress is missing)."""


def mesh_sha256(nodes_mm: np.ndarray, tets: np.ndarray) -> str:
    """SHA-256 of a mesh's nodes (float64) and elements (int64), little-endian bytes."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(nodes_mm, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(tets, dtype="<i8").tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class SweepModel:
    """A calibrated model: stress-free mesh, material, load and support.

    Attributes
    ----------
    nodes_mm : ndarray, shape (n_nodes, 3)
        Stress-free reference geometry, reference-scan frame, mm.
    tets : ndarray of int, shape (n_tets, 4)
    back_nodes, surface_nodes : ndarray of int
        Node sets ``back`` (the support) and ``surface`` (the boundary without the back).
    nipple_node : int
    c1_pa : float
        Calibrated c1: every solve runs at this c1 (other c1 by scaled gravity).
    nu, density_kg_m3, g_m_s2 : float
    formulation : str
    support : {"clamped", "sliding"}
    reference_state : str
    R_ref_from_phantom : ndarray, shape (3, 3)
        Phantom frame of posture angles in the reference-scan frame.
    tumour_stress_free_mm : ndarray, shape (3,) or None
        Where the tumour is in ``nodes_mm`` (the stress-free mesh; the loaded mesh for a
        prestressed reference).
    prestress_state : ndarray, shape (n_dofs,) or None
        A prestressed reference: the inverse state of the spatial recovery on
        ``nodes_mm`` (the loaded mesh); None for a straight stress-free mesh.
    prestress_gravity_m_s2 : ndarray, shape (3,) or None
        The reference scan's gravity (model frame, m/s^2) the prestress balances.
    region : ndarray of int, shape (n_tets,) or None
        Region tag per element (None: one region, ``bulk``).
    region_names : dict of str to int or None
    effects : dict or None
        A diagnosis refit's ``named`` effects and their ``values``
        (:meth:`calib.model.effects.EffectValues.as_json`); None: the homogeneous
        neo-Hookean calibration.
    law : str
        The record's ``model.law``.
    source : dict
        Paths of the calibration files (for provenance).
    """

    nodes_mm: np.ndarray
    tets: np.ndarray
    back_nodes: np.ndarray
    surface_nodes: np.ndarray
    nipple_node: int
    c1_pa: float
    nu: float
    density_kg_m3: float
    g_m_s2: float
    formulation: str
    support: str
    reference_state: str
    R_ref_from_phantom: np.ndarray
    tumour_stress_free_mm: np.ndarray | None = None
    prestress_state: np.ndarray | None = field(default=None, compare=False)
    prestress_gravity_m_s2: np.ndarray | None = field(default=None, compare=False)
    region: np.ndarray | None = field(default=None, compare=False)
    region_names: dict | None = None
    effects: dict | None = None
    law: str = _NEO_HOOKEAN
    source: dict = field(default_factory=dict, compare=False)

    @property
    def flipped_elements(self) -> np.ndarray:
        """Elements of the stress-free mesh inverted against the rest (flipped for solving).

        A straight stress-free reference that calibrate recovered may hold a few at the
        clamped rim (``calibration.json`` ``reference_recovery.inverted_elements``): in the
        reference scan's own posture they are right side out, a state no forward solve
        from the stress-free mesh reaches (their volume would pass through zero), so
        scenarios near that posture may fail there (review BP, P3: an independent
        generator's calibration with 9 failed at 0, 10, 345 and 355 degrees, each at one of
        them; the README's sweep of the quick twin, whose reference holds 3, reports no such
        failure). Empty for a prestressed reference or a mesh of one orientation.
        """
        from fem.mesh import TetMesh

        if self.prestress_state is not None:
            return np.zeros(0, dtype=np.int64)
        one = np.ones(len(self.tets), dtype=np.int64)
        return TetMesh(self.nodes_mm, self.tets, one, {"bulk": 1}, {}).against_the_rest()

    @property
    def scales_with_c1(self) -> bool:
        """Whether a solve at c1 equals one at the calibrated c1 with gravity scaled.

        True unless the back plate is held by tangential springs (Pa/mm), whose stiffness
        does not scale with c1: every other effect's parameter is a ratio to c1 or nu.
        """
        k = (self.effects or {}).get("values", {}).get("support_stiffness_pa_per_mm", "inf")
        return k == "inf" or float(k) == 0.0

    @property
    def key(self) -> str:
        """Identity of the model (mesh and physics) for caches and store checks."""
        h = hashlib.sha256(self.mesh_sha256.encode())
        h.update(json.dumps(self.physics(), sort_keys=True).encode())
        return h.hexdigest()

    @property
    def mesh_sha256(self) -> str:
        """:func:`mesh_sha256` of the stress-free mesh."""
        return mesh_sha256(self.nodes_mm, self.tets)

    def physics(self) -> dict:
        """Material, load and support as JSON numbers (the store's ``model`` block)."""
        t = self.tumour_stress_free_mm
        doc = {
            "law": self.law,
            "c1_pa": self.c1_pa,
            "nu": self.nu,
            "density_kg_m3": self.density_kg_m3,
            "g_m_s2": self.g_m_s2,
            "formulation": self.formulation,
            "support": self.support,
            "reference_state": self.reference_state,
            "R_ref_from_phantom": np.asarray(self.R_ref_from_phantom).tolist(),
            "nipple_node": int(self.nipple_node),
            "tumour_stress_free_mm": None if t is None else np.asarray(t).tolist(),
            "prestress": None
            if self.prestress_state is None
            else {
                "mesh": "loaded reference mesh (mesh/nodes_mm)",
                "state_sha256": hashlib.sha256(
                    np.ascontiguousarray(self.prestress_state, dtype="<f8").tobytes()
                ).hexdigest(),
                "gravity_m_s2": np.asarray(self.prestress_gravity_m_s2).tolist(),
            },
        }
        if self.effects:  # absent otherwise: the stores of plain calibrations keep their key
            tags = np.ascontiguousarray(self.region, dtype="<i8").tobytes()
            doc["effects"] = self.effects | {"regions_sha256": hashlib.sha256(tags).hexdigest()}
        return doc

    def tet_mesh(self):
        """The :class:`fem.TetMesh` (positively oriented) with its node sets."""
        import fem

        one = self.region is None
        mesh = fem.TetMesh(
            self.nodes_mm,
            self.tets,
            np.ones(len(self.tets), dtype=np.int64) if one else self.region,
            {"bulk": 1} if one else self.region_names,
            {
                "back": self.back_nodes,
                "surface": self.surface_nodes,
                "nipple": np.array([self.nipple_node]),
            },
        )
        return mesh.oriented()

    def prestress(self, fm, disc):
        """The :class:`fem.prestress.Prestress` of a prestressed reference (None otherwise).

        Rebuilt by the spatial inverse from the saved state: at the calibrated c1 that
        state is already the solution (no Newton step beyond the residual check).
        """
        if self.prestress_state is None:
            return None
        from fem.prestress import compute_prestress

        g = np.asarray(self.prestress_gravity_m_s2, float)
        mag = float(np.linalg.norm(g))
        return compute_prestress(
            fm,
            gravity=g / mag,
            g_m_s2=mag,
            method="inverse",
            disc=disc,
            x0_state=self.prestress_state,
        )

    def fem_model(self):
        """The :class:`fem.Model` at the calibrated c1: homogeneous, or with the effects."""
        import fem

        if self.effects:
            from ..model.effects import EffectValues, effect_model

            values = EffectValues.from_json(self.effects["values"])
            return effect_model(self.tet_mesh(), self.c1_pa, values)
        supports = {"clamped": fem.Clamped(), "sliding": fem.Sliding()}
        material = fem.NeoHookean(self.c1_pa, nu=self.nu)
        return fem.Model.homogeneous(
            self.tet_mesh(),
            material,
            density_kg_m3=self.density_kg_m3,
            support=supports[self.support],
        )


def _fail(path: Path, what: str) -> None:
    raise CalibrationMissingError(f"{path}: {what}")


def _read_model_mesh(path: Path):
    """A model mesh written by ``calibrate``, with its ``back`` and ``surface`` node sets."""
    from fem.io import read_mesh

    mesh = read_mesh(path, orient=False)
    for name in ("back", "surface"):
        if name not in mesh.node_sets or not len(mesh.node_sets[name]):
            _fail(path, f"no node set 'set:{name}' in the point data")
    return mesh


def load_sweep_model(work: str | Path) -> SweepModel:
    """The calibrated model of ``work`` (see the module docstring).

    Parameters
    ----------
    work : path
        A work folder written by ``phantom-calib calibrate``.

    Returns
    -------
    SweepModel

    Raises
    ------
    CalibrationMissingError
        No ``calibration.json``, a record without a ``model`` block or one of its keys,
        or no reference mesh beside it.
    ValueError
        A record of the wrong shape, or a c1 that is not a positive number
        (:func:`calib.data.work.check_record`).
    calib.io.StaleOutputError
        ``calibration/`` is not from the run recorded in ``calibration.json``.
    UnsupportedReferenceError
        A prestressed reference whose record names no prestress files (a calibration
        of an older version).
    """
    from ..data.work import check_record, not_a_folder
    from ..io import check_run

    work = Path(work)
    record = work / "calibration.json"
    if why := not_a_folder(work):
        raise CalibrationMissingError(f"{work}: {why}")
    try:
        doc = check_run(work, folder="calibration", record="calibration.json")
    except FileNotFoundError:
        raise CalibrationMissingError(
            f"{record} not found: {work} holds no calibration (run `phantom-calib calibrate "
            f"SCANS --out {work}` first)"
        ) from None
    # c1_pa and the keys every reader uses, nu, density, g and the rotation among them
    # (review AC: c1 -5 or NaN swept every scenario to a failure and exited 0)
    check_record(doc, record)
    model = doc.get("model")
    if not isinstance(model, dict):
        _fail(record, "no 'model' block (written by phantom-calib calibrate >= 0.1 with schema 1)")
    method = (doc.get("reference_recovery") or {}).get("method")
    pre = model.get("prestress")
    if (doc.get("reference_state") == "prestress" or method == "spatial") and not pre:
        raise UnsupportedReferenceError(
            f"{record}: the calibration's reference is the prestressed loaded mesh "
            "(reference_recovery.method 'spatial') but its model block names no prestress "
            "files (model.prestress): recalibrate with this version"
        )
    missing = [k for k in _REQUIRED if model.get(k) is None]
    if missing:
        _fail(record, f"model block lacks {', '.join(missing)}")
    if model["support"] not in _SUPPORTS:
        _fail(record, f"model.support {model['support']!r} is not one of {_SUPPORTS}")
    mesh_path = work / model["reference_mesh"]
    if not mesh_path.is_file():
        _fail(mesh_path, "reference mesh named in calibration.json not found")
    mesh = _read_model_mesh(mesh_path)
    R = np.asarray(model["R_ref_from_phantom"], float)  # a rotation: check_record
    nipple = model["nipple_node"]
    if (
        isinstance(nipple, bool)
        or not isinstance(nipple, int)
        or not 0 <= nipple < len(mesh.nodes_mm)
    ):
        # review AD: 10**6 failed after the first solve (a traceback), -1 meant the last node
        _fail(record, f"model.nipple_node {nipple!r} is not a node of {mesh_path.name}")
    tumour = model.get("tumour_stress_free_mm")
    state = g_pre = None
    if pre:
        loaded_path, state_path = work / pre["mesh"], work / pre["state"]
        for path in (loaded_path, state_path):
            if not path.is_file():
                _fail(path, "prestress file named in calibration.json (model.prestress) not found")
        mesh = _read_model_mesh(loaded_path)
        with np.load(state_path) as z:
            state, g_pre = np.asarray(z["inverse_state"], float), np.asarray(z["gravity_m_s2"])
        tumour = pre.get("tumour_reference_mm")
    if tumour is not None:  # review AD: one outside the mesh failed every scenario, exit 0
        try:
            t = np.asarray(tumour, float) if isinstance(tumour, list) else np.full(1, np.nan)
        except (TypeError, ValueError):
            t = np.full(1, np.nan)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            _fail(record, f"the tumour centre {tumour!r} is not a finite point (x, y, z mm)")
        from fem.probe import contains

        if not contains(mesh, t):  # as the engine's MaterialPoint.locate finds it
            _fail(record, f"the tumour centre {t.tolist()} (mm) lies outside the model mesh")
    effects = _effects(record, model, mesh, mesh_path, float(doc["c1_pa"]))
    return SweepModel(
        nodes_mm=mesh.nodes_mm,
        tets=mesh.tets,
        back_nodes=mesh.node_sets["back"],
        surface_nodes=mesh.node_sets["surface"],
        nipple_node=int(model["nipple_node"]),
        c1_pa=float(doc["c1_pa"]),
        nu=float(model["nu"]),
        density_kg_m3=float(model["density_kg_m3"]),
        g_m_s2=float(model["g_m_s2"]),
        formulation=str(model["formulation"]),
        support=str(model["support"]),
        reference_state=str(doc.get("reference_state", "unload")),
        R_ref_from_phantom=R,
        tumour_stress_free_mm=None if tumour is None else np.asarray(tumour, float),
        prestress_state=state,
        prestress_gravity_m_s2=g_pre,
        region=None if effects is None else mesh.region,
        region_names=None if effects is None else dict(mesh.region_names),
        effects=effects,
        law=str(model.get("law") or _NEO_HOOKEAN) if effects else _NEO_HOOKEAN,
        # review BT: a prestressed model is solved on the loaded mesh and its inverse
        # state, which its provenance then names (the stress-free mesh is not read)
        source={"calibration.json": record}
        | (
            {"reference_mesh.vtu": mesh_path}
            if not pre
            else {loaded_path.name: loaded_path, state_path.name: state_path}
        ),
    )


def _effects(record: Path, model: dict, mesh, mesh_path: Path, c1_pa: float) -> dict | None:
    """A diagnosis refit's ``model.effects`` (``named``, ``values``), checked; None if none.

    Review AT: the sweep solved a refit with a named skin as the homogeneous body at the
    refitted c1 (44 % more nipple displacement), without a word.
    """
    from ..model.effects import LIBRARY, EffectError, EffectValues, effect_model

    eff = model.get("effects")
    if eff is None:
        return None
    named = eff.get("named") if isinstance(eff, dict) else None
    if not isinstance(named, list) or not all(isinstance(n, str) for n in named):
        _fail(record, f"model.effects.named is {named!r}: not a list of effect names")
    if not named:
        return None
    unknown = sorted(set(named) - set(LIBRARY))
    if unknown:
        _fail(record, f"model.effects.named: {unknown} are not effects of the library "
                      f"({sorted(LIBRARY)})")  # fmt: skip
    raw = eff.get("values")
    try:
        values = EffectValues.from_json(raw)
    except (EffectError, TypeError, ValueError, AttributeError) as exc:
        _fail(record, f"model.effects.values {raw!r}: {exc}")
    for key in ("nu", "density_kg_m3"):  # the model block's, which the store records
        if not np.isclose(getattr(values, key), float(model[key]), rtol=1e-12, atol=0.0):
            _fail(record, f"model.effects.values.{key} {getattr(values, key)!r} differs from "
                          f"model.{key} {model[key]!r}")  # fmt: skip
    try:
        effect_model(mesh, c1_pa, values)
    except EffectError as exc:
        _fail(mesh_path, f"its regions do not carry the named effects ({named}): {exc}")
    regional = {"skin": "skin", "inclusions": "inclusion"}
    names = {n.split(":")[0] for n in mesh.region_names}
    lost = [e for e in named if e in regional and regional[e] not in names]
    if lost:
        _fail(mesh_path, f"no {', '.join(regional[e] for e in lost)} region for the named "
                         f"{', '.join(lost)} (cell data 'region' and its names)")  # fmt: skip
    return {"named": list(named), "values": values.as_json()}
