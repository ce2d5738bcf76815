"""Surrogate trust: our surrogate against FE at gravity directions it was not trained near.

Review BP (P6): the direction checks warn of a query farther from every training
direction than a limit (:func:`nn.surrogate.direction_limit_deg`) or outside the hull of
the training directions around it (:func:`nn.surrogate.outside_hull_deg`); the first was
measured on twin stores only. This prints, for a calibrated work folder (by default
the quick twin), what a query costs as it moves away from the training directions, and
whether it is warned of:

- on the ``dissertation`` plan (two great circles 15 degrees apart on each), directions
  an angle ``theta`` off both circles (``|u_x| = |u_y| = sin theta`` in the phantom frame,
  two per angle, on opposite sides);
- on the same plan, a transverse posture between two training angles (37.5 degrees)
  tilted out of its circle;
- on a ``sphere:N`` plan (all for training), the directions farthest from every training
  direction (the lattice's holes, found among seeded random directions), where a query
  anywhere on the sphere can lie.

Each row is one FE solve (cold start, the sweep's own solver and model) against the
surrogate's prediction: the surface vertices' error, mean and max (mm), and the mean
error as a share of the mean surface displacement.

    python benchmarks/bench_surrogate_trust.py [--work WORK] [--root DIR] [--sphere 100]
                                               [--seed 0]

Stores are built in ``--root`` when missing (``phantom-calib sweep``, pool of 2) and
reused otherwise; ``--work`` defaults to the quick twin calibrated there.
"""

from __future__ import annotations

import argparse
import tempfile
import warnings
from pathlib import Path

import numpy as np
from _provenance import FE, print_header
from bench_surrogate import sweep
from bench_sweep import calibrated_twin, machine


def off_both_circles(theta_deg: float) -> list[np.ndarray]:
    """Two unit directions (phantom frame) ``theta_deg`` off the x-z and the y-z planes."""
    s = np.sin(np.radians(theta_deg))
    c = np.sqrt(max(0.0, 1.0 - 2.0 * s * s))
    return [np.array([s, s, c]), np.array([s, -s, -c])]


def off_the_transverse_circle(phi_deg: float, angle_deg: float = 37.5) -> list[np.ndarray]:
    """A transverse posture angle (phantom frame) tilted ``phi_deg`` out of its plane."""
    a, p = np.radians(angle_deg), np.radians(phi_deg)
    return [np.cos(p) * np.array([np.cos(a), 0.0, np.sin(a)]) + np.sin(p) * np.array([0, 1.0, 0])]


def sphere_holes(train_dirs: np.ndarray, n: int, seed: int) -> list[np.ndarray]:
    """The ``n`` seeded random directions farthest from every training direction."""
    from scipy.spatial import cKDTree

    q = np.random.default_rng(seed).normal(size=(20_000, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    d = cKDTree(train_dirs).query(q)[0]
    return list(q[np.argsort(d)[::-1][:n]])


def measure(work: Path, data, surrogate, directions_phantom: list[np.ndarray]) -> list[dict]:
    """FE against the surrogate at each direction (phantom frame, the sweep's c1 and g)."""
    from calib.sweep import load_sweep_model
    from calib.sweep.engine import ScenarioTask, solve_scenario
    from nn.surrogate import outside_hull_deg

    model = load_sweep_model(work)
    R = np.asarray(data.model["R_ref_from_phantom"])
    train = data.subset(data.role == "train").gravity_phantom
    train = train / np.linalg.norm(train, axis=1, keepdims=True)
    rows = []
    for k, u in enumerate(directions_phantom):
        u = u / np.linalg.norm(u)
        near = float(np.degrees(np.arccos(np.clip(train @ u, -1.0, 1.0))).min())
        trained = surrogate.meta["trained"]  # the surrogate's own frame and directions
        dirs_ref = np.asarray(trained["directions_ref"], float)
        outside = float(
            outside_hull_deg((R @ u)[None], dirs_ref, trained["direction_spacing_deg"])[0]
        )
        task = ScenarioTask(index=k, gravity_ref=R @ u, g_m_s2=model.g_m_s2, x0=None)
        r = solve_scenario(model, model.key, task)
        if not r.ok:
            rows.append({"nearest_deg": near, "outside_deg": outside, "failed": r.message[:80]})
            continue
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            p = surrogate.predict(u * model.g_m_s2, frame="phantom")
        fe = r.displacement_mm[data.surface_nodes]
        err = np.linalg.norm(p.surface_mm[0] - fe, axis=1)
        rows.append(
            {
                "nearest_deg": near,
                "outside_deg": outside,
                "warned": any("training direction" in str(w.message) for w in caught),
                "mean_mm": float(err.mean()),
                "max_mm": float(err.max()),
                "share": float(err.mean() / np.linalg.norm(fe, axis=1).mean()),
                "disp_max_mm": float(np.linalg.norm(fe, axis=1).max()),
            }
        )
    return rows


def print_rows(label: str, rows: list[dict], limit: float) -> None:
    for r in rows:
        if "failed" in r:
            print(
                f"| {label} | {r['nearest_deg']:.1f} | {limit:.1f} | {r['outside_deg']:.1f} | "
                "– | no FE solution |"
            )
            continue
        print(
            f"| {label} | {r['nearest_deg']:.1f} | {limit:.1f} | {r['outside_deg']:.1f} | "
            f"{'yes' if r['warned'] else 'no'} | {r['mean_mm']:.4f} | {r['max_mm']:.4f} | "
            f"{100 * r['share']:.2f} % | {r['disp_max_mm']:.1f} |"
        )


def main() -> None:
    import torch

    import nn
    from nn.surrogate import direction_limit_deg

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--root", type=Path, default=None)
    ap.add_argument("--sphere", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0, help="seed of the sphere's hole search")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print_header(("torch", "zarr", *FE))
    print(machine())
    with tempfile.TemporaryDirectory() as tmp:
        root = args.root or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        work = args.work or calibrated_twin(root)
        diss = nn.load_sweep(sweep(work, root / "sweep-dissertation", plan="dissertation"))
        sph = nn.load_sweep(
            sweep(work, root / f"sweep-sphere{args.sphere}", plan=f"sphere:{args.sphere}")
        )
        print()
        print(
            "| plan, query | nearest training direction deg | limit deg | outside the "
            "neighbours' hull deg (limit 1) | warned | surface error mean mm | max mm | "
            "mean / displacement | FE displacement max mm |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for name, data in (("dissertation", diss), (f"sphere:{args.sphere}", sph)):
            sur = nn.Surrogate.from_fit(nn.fit_reduced_kernel(data, device="cpu"), data)
            trained = sur.meta["trained"]
            limit = direction_limit_deg(
                trained["direction_spacing_deg"], trained.get("validated_direction_deg")
            )
            e = sur.report["errors"].get("validation")
            if e and e.get("n"):
                print(
                    f"| {name}, its {e['n']} validation directions | – | {limit:.1f} | – | – | "
                    f"{e['surface_mean_mm']:.2g} | {e['surface_max_mm']:.2g} | – | – |"
                )
            if name == "dissertation":
                for theta in (5, 10, 15, 20, 25, 29, 35, 45):
                    rows = measure(work, data, sur, off_both_circles(theta))
                    print_rows(f"dissertation, {theta} deg off both circles", rows, limit)
                for phi in (0.5, 1, 2, 5, 10, 15, 20):
                    rows = measure(work, data, sur, off_the_transverse_circle(phi))
                    print_rows(f"dissertation, transverse 37.5 deg tilted {phi} deg", rows, limit)
            else:
                train = data.subset(data.role == "train").gravity_phantom
                train = train / np.linalg.norm(train, axis=1, keepdims=True)
                rows = measure(work, data, sur, sphere_holes(train, 4, args.seed))
                print_rows(f"{name}, a hole of the lattice", rows, limit)


if __name__ == "__main__":
    main()
