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
    source: dict = field(default_factory=dict, compare=False)

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
        return {
            "law": "neo-hookean (uncoupled), W = c1 (I1bar - 3) + U(J)",
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

    def tet_mesh(self):
        """The :class:`fem.TetMesh` (positively oriented) with its node sets."""
        import fem

        mesh = fem.TetMesh(
            self.nodes_mm,
            self.tets,
            np.ones(len(self.tets), dtype=np.int64),
            {"bulk": 1},
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
        """The homogeneous :class:`fem.Model` at the calibrated c1."""
        import fem

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
    """
    from ..data.work import check_record
    from ..io import check_run

    work = Path(work)
    record = work / "calibration.json"
    if not work.is_dir():
        raise CalibrationMissingError(f"{work}: no such work folder")
    try:
        doc = check_run(work, folder="calibration", record="calibration.json")
    except FileNotFoundError:
        raise CalibrationMissingError(
            f"{record} not found: {work} holds no calibration (run `phantom-calib calibrate "
            f"SCANS --out {work}` first)"
        ) from None
    check_record(doc, record)  # c1_pa and the keys every reader uses
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
    for key, value, ok in (
        ("model.nu", model["nu"], lambda v: 0 < v < 0.5),
        ("model.density_kg_m3", model["density_kg_m3"], lambda v: v > 0),
        ("model.g_m_s2", model["g_m_s2"], lambda v: v > 0),
    ):  # review AC: c1 -5 or NaN swept every scenario to a failure and exited 0
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not (number and np.isfinite(value) and ok(value)):
            _fail(record, f"{key} is {value!r}: not a finite number in its physical range")
    if model["support"] not in _SUPPORTS:
        _fail(record, f"model.support {model['support']!r} is not one of {_SUPPORTS}")
    mesh_path = work / model["reference_mesh"]
    if not mesh_path.is_file():
        _fail(mesh_path, "reference mesh named in calibration.json not found")
    mesh = _read_model_mesh(mesh_path)
    R = np.asarray(model["R_ref_from_phantom"], float)
    rotation = R.shape == (3, 3) and np.allclose(R.T @ R, np.eye(3), atol=1e-9)
    if not (rotation and np.linalg.det(R) > 0):  # review AD: a mirror passed
        _fail(record, "model.R_ref_from_phantom is not a 3x3 rotation (orthonormal, det +1)")
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
        source={"calibration.json": record, "reference_mesh.vtu": mesh_path},
    )
