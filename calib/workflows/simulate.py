"""``phantom-calib simulate``: one gravity solve on a user's mesh."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import fem
from fem.meshing import find_back_plane, tag_node_sets
from fem.units import STANDARD_GRAVITY_M_S2

from ..io import atomic_write, provenance, write_json_atomic

__all__ = ["SimulateOptions", "parse_back_plane", "parse_vector", "run_simulate"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimulateOptions:
    """Options of the ``simulate`` command (see the README for their meaning)."""

    c1_pa: float
    nu: float = 0.499
    density_kg_m3: float = 1000.0
    gravity: tuple[float, float, float] = (0.0, 1.0, 0.0)
    g_m_s2: float = STANDARD_GRAVITY_M_S2
    bc: str = "clamped"
    back_plane: str = "auto"
    formulation: str = "taylor-hood"


def parse_vector(text: str) -> tuple[float, float, float]:
    """Parse ``"X,Y,Z"`` into a non-zero 3-vector."""
    parts = text.split(",")
    try:
        vec = tuple(float(p) for p in parts)
    except ValueError:
        vec = ()
    if len(vec) != 3 or not np.all(np.isfinite(vec)) or not np.any(vec):
        raise ValueError(f"expected a non-zero vector 'X,Y,Z', got {text!r}")
    return vec  # type: ignore[return-value]


def parse_back_plane(text: str) -> float | None:
    """``auto`` gives None; ``z=VALUE`` gives the plane's z in mm."""
    if text == "auto":
        return None
    if text.startswith("z="):
        try:
            return float(text[2:])
        except ValueError:
            pass
    raise ValueError(f"--back-plane must be 'auto' or 'z=VALUE' (mm), got {text!r}")


def _back_nodes(mesh: fem.TetMesh, z_mm: float | None):
    if z_mm is None:
        nodes, normal, _ = find_back_plane(mesh)
        return nodes, normal
    bnodes = np.unique(fem.boundary_faces(mesh.tets))
    scale = float(np.ptp(mesh.nodes_mm, axis=0).max())
    nodes = bnodes[np.abs(mesh.nodes_mm[bnodes, 2] - z_mm) < 1e-6 * scale + 1e-9]
    if len(nodes) < 3:
        raise fem.MeshError(f"no back face found at z={z_mm} mm (found {len(nodes)} nodes)")
    normal = np.array([0.0, 0.0, -1.0 if mesh.nodes_mm[:, 2].mean() > z_mm else 1.0])
    return nodes, normal


def _model(mesh: fem.TetMesh, opts: SimulateOptions) -> fem.Model:
    material = fem.NeoHookean(opts.c1_pa, nu=opts.nu)
    supports = {"clamped": fem.Clamped(), "sliding": fem.Sliding()}
    if opts.bc not in supports:
        raise ValueError(f"--bc must be 'clamped' or 'sliding', got {opts.bc!r}")
    return fem.Model.homogeneous(
        mesh, material, density_kg_m3=opts.density_kg_m3, support=supports[opts.bc]
    )


def run_simulate(mesh_path: Path, out_path: Path, opts: SimulateOptions) -> dict:
    """Solve the gravity load on a mesh file and write ``out_path`` and its ``.json``.

    Returns
    -------
    dict
        The summary written to ``RESULT.json``.
    """
    from fem.io import read_mesh, write_mesh

    if opts.density_kg_m3 <= 0:
        raise ValueError(f"--density must be positive, got {opts.density_kg_m3}")
    t0 = time.perf_counter()
    mesh = read_mesh(mesh_path).oriented()
    back, normal = _back_nodes(mesh, parse_back_plane(opts.back_plane))
    mesh = tag_node_sets(mesh, back, normal)
    model = _model(mesh, opts)
    sol = fem.solve(model, gravity=np.array(opts.gravity), g_m_s2=opts.g_m_s2,
                    formulation=opts.formulation)  # fmt: skip
    nipple = int(mesh.node_set("nipple")[0])
    summary = {
        "max_displacement_mm": sol.max_displacement_mm,
        "nipple_displacement_mm": float(np.linalg.norm(sol.displacement_mm[nipple])),
        "nipple_node": nipple,
        "converged": sol.converged,
        "newton_iterations": sol.newton_iterations,
        "load_steps": sol.load_steps,
        "dofs": sol.dofs,
        "wall_s": time.perf_counter() - t0,
        "formulation": sol.formulation,
        "provenance": provenance(inputs={"mesh": mesh_path}, parameters=opts.__dict__),
    }
    json_path = out_path.with_suffix(".json")
    deformed = mesh.with_nodes(mesh.nodes_mm + sol.displacement_mm)
    atomic_write(out_path, lambda p: write_mesh(
        deformed, p, point_data={"displacement_mm": sol.displacement_mm}))  # fmt: skip
    write_json_atomic(json_path, summary)
    return summary
