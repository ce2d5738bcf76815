"""The twin's stiff inclusions: conforming spheres against elements tagged by centroid.

The twin renders its inclusions as spheres. Until a61d6e2 its truth model made the
elements whose centroid lay in a sphere stiffer instead. This script measures what that
did to the hidden effect: for each seed it meshes the quick twin's phantom both ways
(``fem.meshing.mesh_phantom``'s ``embed_inclusions``), solves the twin's four postures
(the gravity directions ``calib.twin.synthesize`` draws for that seed) with the
inclusions at the bulk's stiffness and at ``--ratio`` times it, and prints per posture

* the inclusions' surface print on each mesh: the signed normal distance between the
  deformed surfaces with and without the stiff inclusions, at the tagged mesh's surface
  nodes off the back plate (rms and largest, mm);
* the tagged print against the conforming one: the least-squares slope, the correlation
  and the rms of their difference;

and per seed the stiff volume of each mesh against the spheres' (mm3).

    python benchmarks/bench_twin_inclusions.py [--seeds 0] [--ratio 30] [--finer MM]

With ``--finer MM`` the twin's own conforming mesh is compared instead with a conforming
mesh of MM elements (the columns "tagged" then read "twin", "conforming" the finer
mesh): whether the twin's stiff-inclusion print is converged in its mesh.

One solve per posture and mesh; the conforming mesh (about 36,000 elements on the quick
twin) takes most of the time, a few minutes per seed on one core.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _provenance import FE, print_header

import fem
from calib.model.effects import TruthEffects, truth_model
from calib.model.residuals import closest_on_surface
from calib.twin.synth import G_SCANNER, PRESETS, scanner_poses
from fem.geometry import PhantomSpec, build_phantom
from fem.meshing import mesh_phantom


def _gravities(seed: int, preset) -> dict[str, np.ndarray]:
    """The phantom-frame gravity of each posture, as ``synthesize`` draws them."""
    return {n: T[:3, :3].T @ G_SCANNER for n, T in scanner_poses(preset, seed).items()}


def _surfaces(mesh: fem.TetMesh, ratio: float, gravities: dict, c1_pa: float) -> dict:
    """Deformed boundary (vertices, faces) per posture."""
    model = truth_model(mesh, c1_pa, TruthEffects(inclusion_ratio=ratio))
    disc = fem.discretize(mesh, model.support, formulation="taylor-hood")
    faces = fem.boundary_faces(mesh.tets)
    return {
        name: (mesh.nodes_mm + fem.solve(model, gravity=g, disc=disc).displacement_mm, faces)
        for name, g in gravities.items()
    }


def _signed(surface, points: np.ndarray) -> np.ndarray:
    c, _, _, n = closest_on_surface(*surface, points)
    return np.einsum("kj,kj->k", points - c, n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--ratio", type=float, default=30.0)
    ap.add_argument(
        "--finer",
        type=float,
        default=None,
        help="compare the twin's conforming mesh with a conforming one of this size (mm)",
    )
    args = ap.parse_args()
    print_header(FE)
    p = PRESETS["quick"]
    print(f"quick twin, inclusions {args.ratio:g} x the bulk, c1 = {p.c1_pa:g} Pa")
    meshes = [("tagged", False, p.truth_mesh_mm), ("conforming", True, p.truth_mesh_mm)]
    if args.finer is not None:  # the twin's own mesh first: its surface nodes sample
        twin = f"the twin's conforming {p.truth_mesh_mm:g} mm mesh"
        print(f"tagged: {twin}; conforming: {args.finer:g} mm")
        meshes = [("tagged", True, p.truth_mesh_mm), ("conforming", True, args.finer)]
    print(
        f"{'seed':>4} {'posture':14s} {'tagged rms':>10} {'max':>6} {'conform rms':>11} "
        f"{'max':>6} {'slope':>6} {'corr':>5} {'diff rms':>8}"
    )
    for seed in (int(s) for s in args.seeds.split(",")):
        t0 = time.perf_counter()
        phantom = build_phantom(PhantomSpec(resolution_mm=p.phantom_resolution_mm, seed=seed))
        gravities = _gravities(seed, p)
        prints, volumes = {}, {}
        for label, embed, size in meshes:
            mesh = mesh_phantom(
                phantom, size_mm=size, skin_thickness_mm=0.0, embed_inclusions=embed
            )
            inside = mesh.region == fem.mesh.REGION_IDS["inclusion"]
            volumes[label] = (mesh.volumes_mm3()[inside].sum(), mesh.n_tets)
            soft = _surfaces(mesh, 1.0, gravities, p.c1_pa)
            stiff = _surfaces(mesh, args.ratio, gravities, p.c1_pa)
            if label == "tagged":  # the sample points: its surface nodes off the plate
                surface_nodes = np.unique(fem.boundary_faces(mesh.tets))
                off = surface_nodes[mesh.nodes_mm[surface_nodes, 2] > 1e-6]
                points = {n: soft[n][0][off] for n in gravities}
            prints[label] = {
                n: _signed(stiff[n], points[n]) - _signed(soft[n], points[n]) for n in gravities
            }
        for name in gravities:
            a, b = prints["tagged"][name], prints["conforming"][name]
            rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
            print(
                f"{seed:>4} {name:14s} {rms(a):10.3f} {np.abs(a).max():6.3f} {rms(b):11.3f} "
                f"{np.abs(b).max():6.3f} {a @ b / (b @ b):6.2f} {np.corrcoef(a, b)[0, 1]:5.2f} "
                f"{rms(a - b):8.3f}"
            )
        spheres = float((np.pi / 6 * phantom.inclusion_diameters_mm**3).sum())
        print(
            f"     stiff volume: tagged {volumes['tagged'][0]:.0f} mm3 "
            f"({volumes['tagged'][1]} elements), conforming {volumes['conforming'][0]:.0f} "
            f"mm3 ({volumes['conforming'][1]} elements), spheres {spheres:.0f} mm3; "
            f"{time.perf_counter() - t0:.0f} s"
        )


if __name__ == "__main__":
    main()
