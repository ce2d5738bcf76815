"""A tiny calibrated work folder (no scans, no calibration run) for sweep and nn tests.

``make_box_work`` writes what ``phantom-calib calibrate`` writes for a sweep to read: a
``calibration.json`` with ``c1_pa``, ``reference_state`` and the ``model`` block, and
``calibration/reference_mesh.vtu`` (node sets ``back``, ``surface``, ``nipple``), as one
run (:class:`calib.io.RunOutputs`). The body is a block clamped at its base z = 0 and the
phantom frame is rotated against the model frame, so that frame mistakes show.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

BOX_C1_PA = 500.0


def rotation_xyz(deg=(20.0, -30.0, 40.0)) -> np.ndarray:
    """A rotation matrix from three angles (degrees) about x, y, z."""
    a, b, c = np.radians(deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def box_mesh(size_mm=(40.0, 40.0, 30.0), n=(3, 3, 4)):
    """A tetrahedral block [0, a] x [0, b] x [0, c] with node sets back (z = 0), surface, nipple."""
    from skfem import MeshTet

    from fem import TetMesh
    from fem.meshing import tag_node_sets

    axes = [np.linspace(0.0, s, k) for s, k in zip(size_mm, n, strict=True)]
    m = MeshTet.init_tensor(*axes)
    mesh = TetMesh(m.p.T.copy(), m.t.T.copy(), np.ones(m.t.shape[1], dtype=int), {"bulk": 1})
    mesh = mesh.oriented()
    back = np.flatnonzero(np.isclose(mesh.nodes_mm[:, 2], 0.0))
    return tag_node_sets(mesh, back, np.array([0.0, 0.0, -1.0]))


def make_box_work(
    work: Path,
    *,
    c1_pa: float = BOX_C1_PA,
    nu: float = 0.49,
    n=(3, 3, 4),
    R_ref_from_phantom: np.ndarray | None = None,
    tumour_mm=(20.0, 20.0, 15.0),
    shift_mm: float = 0.0,
    skin_above_mm: float | None = None,
    effects: dict | None = None,
) -> Path:
    """Write a calibrated work folder of a clamped block (see the module docstring).

    ``skin_above_mm``: the elements whose centroid lies above this height form a region
    ``skin`` (the rest ``bulk``); ``effects``: the record's ``model.effects`` block, as a
    diagnosis refit writes it (``named``, ``values``).
    """
    from calib.io import RunOutputs
    from fem.io import write_mesh

    mesh = box_mesh(n=n)
    if shift_mm:
        mesh = mesh.with_nodes(mesh.nodes_mm + shift_mm)
    if skin_above_mm is not None:
        top = mesh.nodes_mm[mesh.tets].mean(axis=1)[:, 2] > skin_above_mm
        mesh = mesh.with_regions(np.where(top, 2, 1), {"bulk": 1, "skin": 2})
    R = rotation_xyz() if R_ref_from_phantom is None else np.asarray(R_ref_from_phantom)
    doc = {
        "schema_version": 1,
        "c1_pa": c1_pa,
        "reference_state": "unload",
        "model": {
            "law": "neo-hookean (uncoupled), W = c1 (I1bar - 3) + U(J)",
            "nu": nu,
            "density_kg_m3": 1000.0,
            "formulation": "taylor-hood",
            "support": "clamped",
            "g_m_s2": 9.81,
            "reference_scan": "left_lateral",
            "tumour_stress_free_mm": None if tumour_mm is None else list(tumour_mm),
            "nipple_node": int(mesh.node_set("nipple")[0]),
            "R_ref_from_phantom": R.tolist(),
            "reference_mesh": "calibration/reference_mesh.vtu",
        },
    }
    if effects is not None:
        doc["model"]["effects"] = effects
    with RunOutputs(work, folder="calibration", record="calibration.json") as run:
        write_mesh(mesh, run.path("reference_mesh.vtu"))
        run.commit(doc)
    return Path(work)
