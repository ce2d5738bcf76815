"""FE benchmark: the default phantom under lateral 1 g (c1 = 420 Pa, nu = 0.499).

Prints, per mesh size and formulation: DOFs, Newton iterations, load steps, wall time,
peak memory and the nipple displacement with its error against the mesh-converged
answer (Richardson extrapolation of Taylor-Hood on the two finest meshes, stored in
benchmarks/fem_reference.json with the mesh sizes it came from). The felupe peer rows
(MINI and P2 solids on the same meshes) are not implemented yet.

    python benchmarks/bench_fem.py [--sizes 9,6,4] [--max-dofs 150000] [--update-reference]
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np

import fem
from fem.geometry import PhantomSpec, build_phantom
from fem.meshing import mesh_phantom

REFERENCE = Path(__file__).with_name("fem_reference.json")
FORMULATIONS = ("p1", "mini", "taylor-hood")


def _mesh(size_mm: float) -> fem.TetMesh:
    return mesh_phantom(build_phantom(PhantomSpec(resolution_mm=size_mm)), size_mm=size_mm)


def _estimate_dofs(mesh: fem.TetMesh, formulation: str) -> int:
    n_edges = int(1.2 * mesh.n_tets) + mesh.n_nodes  # ~ 6-7 edges per node in tet meshes
    return {"p1": 3 * mesh.n_nodes, "mini": 4 * mesh.n_nodes + 3 * mesh.n_tets,
            "taylor-hood": 3 * (mesh.n_nodes + n_edges) + mesh.n_nodes}[formulation]  # fmt: skip


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_ours(mesh: fem.TetMesh, formulation: str) -> dict:
    model = fem.Model.homogeneous(mesh, fem.NeoHookean(420.0, nu=0.499), density_kg_m3=1000.0)
    t0 = time.perf_counter()
    disc = fem.discretize(mesh, model.support, formulation=formulation)
    sol = fem.solve(model, gravity=[1.0, 0.0, 0.0], disc=disc)
    nip = int(mesh.node_set("nipple")[0])
    return {"dofs": sol.dofs, "newton": sol.newton_iterations, "steps": sol.load_steps,
            "wall_s": time.perf_counter() - t0, "peak_mb": _peak_mb(),
            "nipple_mm": float(np.linalg.norm(sol.displacement_mm[nip]))}  # fmt: skip


def _row(size, mesh, form, r, ref):
    err = "" if ref is None else f"{100 * (r['nipple_mm'] / ref - 1):+7.2f} %"
    return (
        f"{size:>5.1f} {mesh.n_tets:>8d} {form:<12}{r['dofs']:>9d}{r['newton']:>7d}"
        f"{r['steps']:>6d}{r['wall_s']:>9.1f}{r['peak_mb']:>9.0f}{r['nipple_mm']:>10.3f} {err}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="9,6", help="element sizes in mm (comma separated)")
    ap.add_argument("--max-dofs", type=int, default=150_000)
    ap.add_argument("--formulations", default=",".join(FORMULATIONS))
    ap.add_argument(
        "--update-reference",
        action="store_true",
        help="recompute the converged answer from the two finest sizes",
    )
    args = ap.parse_args()
    sizes = [float(s) for s in args.sizes.split(",")]
    ref = json.loads(REFERENCE.read_text())["nipple_mm"] if REFERENCE.exists() else None
    print("size     tets formulation     dofs newton steps   wall s  peak MB  nipple mm  error")
    th = {}
    for size in sizes:
        mesh = _mesh(size)
        for form in args.formulations.split(","):
            if _estimate_dofs(mesh, form) > args.max_dofs:
                print(f"{size:>5.1f} {mesh.n_tets:>8d} {form:<12} skipped (> --max-dofs)")
                continue
            r = run_ours(mesh, form)
            if form == "taylor-hood":
                th[size] = r["nipple_mm"]
            print(_row(size, mesh, form, r, ref), flush=True)
    if args.update_reference and len(th) >= 2:
        (h1, u1), (h2, u2) = sorted(th.items())[:2]
        rich = u1 + (u1 - u2) / ((h2 / h1) ** 2 - 1)  # second-order Taylor-Hood
        REFERENCE.write_text(json.dumps({"nipple_mm": rich, "from_sizes_mm": [h1, h2],
                                         "values_mm": [u1, u2], "method": "Richardson, p=2"},
                                        indent=1) + "\n")  # fmt: skip
        print(f"converged nipple displacement (Richardson): {rich:.3f} mm -> {REFERENCE}")


if __name__ == "__main__":
    main()
