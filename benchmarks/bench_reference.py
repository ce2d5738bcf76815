"""Reference-state benchmark: stress-free recovery and prestress on the twin's scan meshes.

For each digital-twin scan set, mesh size and method, the reference scan's surface is
meshed as the calibration does (``calib``'s ``reference_mesh``) and the reference state
at ``c1 = 420 Pa x factor`` (nu = 0.499, 1000 kg/m^3, clamped back) is computed by:

- ``newton``: ``fem.unload.recover_stress_free(method="newton")``, the inverse Newton on
  straight-sided stress-free elements, with the calibration's bound of 10 load steps;
- ``spatial``: ``recover_stress_free(method="spatial")`` (``fem.prestress`` ``inverse``),
  inverse elastostatics on the loaded mesh with a curved stress-free mesh;
- ``mulf``: ``fem.prestress.compute_prestress(method="mulf")`` (Gee, Foerster & Wall 2010,
  4 load steps, Aitken-relaxed passes to 1e-6 mm);
- ``fixed-point`` (only with ``--fixed-point``): the backward-displacement iteration.

Columns: success, load factor reached (1 when it succeeded), Newton iterations (forward
solves for the fixed point), wall time (median over ``--repeat`` runs, with min-max),
its ratio to ``newton`` on the same mesh in the same run, and the round trip: the largest
distance between the recovered state loaded by ``g0`` and the scan mesh, solved again
from zero displacement (``newton``/``fixed-point``: vertices of the forward solve on the
recovered mesh; ``spatial``: every P2 node of the forward solve on the curved stress-free mesh from
zero displacement; ``mulf``: the displacement when ``g0`` is applied to the prestressed
scan). Timings on a shared machine: read the ratios and the spread.

The twins (``--twin NAME=SCANS,WORK``) come from::

    phantom-calib synth OUT/none --preset quick --seed 0 --effect none
    phantom-calib ingest OUT/none/scans --out OUT/none-work
    phantom-calib synth OUT/skin --preset quick --seed 0
    phantom-calib ingest OUT/skin/scans --out OUT/skin-work

and then::

    python benchmarks/bench_reference.py --twin none=OUT/none/scans,OUT/none-work \\
        --twin skin=OUT/skin/scans,OUT/skin-work [--sizes 8,10,12,14,16] \\
        [--methods newton,spatial,mulf] [--c1-factors 1] [--repeat 3] [--fixed-point]
        [--postures] [--jsonl rows.jsonl] [--max-dihedral default,165]
    python benchmarks/bench_reference.py --table-from rows.jsonl   # tables of saved rows

With ``--max-dihedral 177,165`` (degrees; ``default``: the ``tetgen`` package's own bound),
each size is meshed once per TetGen optimisation bound on the largest dihedral angle
(``calib``'s ``CalibrationOptions.mesh_max_dihedral_deg``, ``calibrate
--mesh-max-dihedral``); the table's ``slivers`` column counts the elements with a
dihedral angle below 5 or above 175 degrees (``fem.mesh_quality``).

With ``--postures``, where ``newton`` succeeds, each other scan's posture is solved from
every method's reference state and its surface vertices compared with ``newton``'s (the
methods solve different discrete problems: the difference is their discretisation
difference, plus MULF's path-dependent prestress).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from _provenance import FE, print_header, saved_commits

import fem
from fem.prestress import compute_prestress, solve_prestressed
from fem.unload import recover_stress_free

C1_PA, NU, DENSITY_KG_M3 = 420.0, 0.499, 1000.0
UNLOAD_OPTIONS = fem.SolverOptions(max_steps=10)  # the calibration's bound


def reference_mesh(scans: Path, work: Path, size_mm: float, max_dihedral_deg=None):
    """The calibration's model mesh of the reference scan, its gravity, the other postures'.

    ``max_dihedral_deg``: TetGen's optimisation bound (None: the ``tetgen`` package's own).
    """
    try:
        from calib.data.measurements import load_measurements
        from calib.data.session import load_session
        from calib.model.reference import reference_mesh as build
    except ImportError:  # the layout before calib's subpackages
        from calib.measurements import load_measurements
        from calib.refmodel import reference_mesh as build
        from calib.session import load_session
    meas = load_measurements(work, load_session(scans))
    ref = meas.reference
    others = {n: np.asarray(s.gravity_ref, float) for n, s in meas.scans.items() if n != ref.name}
    # the layout before calib's subpackages has no bound: passed only when asked for
    kw = {} if max_dihedral_deg is None else {"max_dihedral_deg": max_dihedral_deg}
    return build(ref, size_mm=size_mm, **kw), np.asarray(ref.gravity_ref, float), others


def _model(mesh, c1_pa):
    return fem.Model.homogeneous(mesh, fem.NeoHookean(c1_pa, nu=NU), density_kg_m3=DENSITY_KG_M3)


def run_method(method: str, model, gravity):
    """One run: (row without timing, payload for the round trip)."""
    if method in ("newton", "spatial", "fixed-point"):
        kw = {"options": UNLOAD_OPTIONS} if method != "fixed-point" else {"max_iter": 60}
        rec = recover_stress_free(model, gravity=gravity, method=method, **kw)
        return {"ok": bool(rec.converged), "load_factor": 1.0, "iterations": rec.iterations,
                "inverted_vertex_tets": rec.inverted_elements}, rec  # fmt: skip
    ps = compute_prestress(model, gravity=gravity, method="mulf", options=UNLOAD_OPTIONS)
    return {"ok": True, "load_factor": 1.0, "iterations": ps.newton_iterations,
            "passes": ps.load_steps}, ps  # fmt: skip


def round_trip_mm(method: str, model, gravity, result) -> float:
    """Largest distance (mm) of the reloaded reference from the scan mesh, from scratch."""
    if method in ("newton", "fixed-point"):
        X = result.nodes_mm
        disc = fem.discretize(model.mesh, model.support).with_nodes(X)
        sol = fem.solve(model.with_mesh(disc.mesh), gravity=gravity, disc=disc)
        return float(np.linalg.norm(X + sol.displacement_mm - model.mesh.nodes_mm, axis=1).max())
    if method == "spatial":  # the curved stress-free mesh, loaded from rest
        return fem.prestress.round_trip_mm(model, result.prestress)
    sol = solve_prestressed(model, result, gravity=gravity)
    return float(np.linalg.norm(sol.displacement_mm, axis=1).max())


def posture_positions(method: str, model, result, gravity) -> np.ndarray:
    """Vertex positions (mm) of a posture from a method's reference state."""
    if method in ("newton", "fixed-point"):
        X = result.nodes_mm
        disc = fem.discretize(model.mesh, model.support).with_nodes(X)
        return X + fem.solve(model.with_mesh(disc.mesh), gravity=gravity, disc=disc).displacement_mm
    ps = result.prestress if method == "spatial" else result
    return model.mesh.nodes_mm + solve_prestressed(model, ps, gravity=gravity).displacement_mm


def compare_postures(name, size, model, payloads: dict, postures: dict) -> list[dict]:
    """Surface positions of each posture by each method against ``newton``'s, mm."""
    if payloads.get("newton") is None:
        return []
    surface = model.mesh.node_set("surface")
    rows = []
    for posture, g in postures.items():
        pos = {m: posture_positions(m, model, r, g) for m, r in payloads.items() if r is not None}
        change = np.linalg.norm(pos["newton"] - model.mesh.nodes_mm, axis=1)[surface]
        for m, p in pos.items():
            if m == "newton":
                continue
            d = np.linalg.norm(p - pos["newton"], axis=1)[surface]
            rows.append({"twin": name, "size_mm": size, "posture": posture, "method": m,
                         "posture_change_rms_mm": float(np.sqrt(np.mean(change**2))),
                         "vs_newton_rms_mm": float(np.sqrt(np.mean(d**2))),
                         "vs_newton_max_mm": float(d.max())})  # fmt: skip
    return rows


def print_postures(rows: list[dict]) -> None:
    head = ("twin", "size", "posture", "method", "posture change RMS mm",
            "vs newton RMS mm", "vs newton max mm")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(f"| {r['twin']} | {r['size_mm']:g} | {r['posture']} | {r['method']} | "
              f"{r['posture_change_rms_mm']:.2f} | {r['vs_newton_rms_mm']:.3f} | "
              f"{r['vs_newton_max_mm']:.3f} |")  # fmt: skip


def bench_case(name, mesh, gravity, size, factor, methods, repeat, postures=None, bound=None):
    """Rows of one mesh and c1; with ``postures``, also the posture comparison rows.

    ``bound``: the mesh's TetGen bound on the largest dihedral angle (None: the package's).
    """
    rows, payloads = [], {}
    slivers = fem.mesh_quality(mesh).n_slivers
    model = _model(mesh, C1_PA * factor)
    times = {m: [] for m in methods}
    last: dict = {}  # each method's last run: (row, payload)
    for _ in range(repeat):  # the methods take turns: load drifts hit all alike (review BL)
        for method in methods:
            if method in last and not last[method][0]["ok"]:
                continue  # a failure is deterministic: not repeated
            t0 = time.perf_counter()
            try:
                row, payload = run_method(method, model, gravity)
            except fem.ConvergenceError as exc:
                row = {
                    "ok": False,
                    "load_factor": getattr(exc, "load_factor", float("nan")),
                    "iterations": getattr(exc, "iterations", None),
                    "failure": str(exc),
                }
                payload = None
            times[method].append(time.perf_counter() - t0)
            last[method] = row, payload
    for method in methods:
        (row, payload), times_m = last[method], times[method]
        row.update(twin=name, size_mm=size, tets=mesh.n_tets, c1_pa=C1_PA * factor,
                   method=method, wall_s=float(np.median(times_m)), wall_min_s=min(times_m),
                   wall_max_s=max(times_m), runs=len(times_m))  # fmt: skip
        row.update(max_dihedral_deg=bound, slivers=slivers)
        row["round_trip_mm"] = round_trip_mm(method, model, gravity, payload) if payload else None
        payloads[method] = payload
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    ref = next((r for r in rows if r["method"] == "newton"), None)
    for r in rows:  # no ratio to a failed Newton run (the table prints "–")
        r["ratio_to_newton"] = r["wall_s"] / ref["wall_s"] if ref and ref["ok"] else None
    compared = compare_postures(name, size, model, payloads, postures) if postures else []
    return rows, compared


def _fmt(v, spec):
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def _mesh_key(r: dict) -> tuple:
    return r["twin"], r["size_mm"], r.get("max_dihedral_deg"), r["c1_pa"]


def print_table(rows: list[dict]) -> None:
    head = ("twin", "size", "TetGen -o/", "tets", "slivers", "c1 Pa", "method", "ok", "load f.",
            "Newton", "wall s (min-max)", "x newton", "round trip mm")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    # the Newton row of each mesh and c1: where it failed, "–" instead of a ratio to it
    newton = {_mesh_key(r): r for r in rows if r["method"] == "newton"}
    for r in rows:
        failed = not newton.get(_mesh_key(r), {"ok": True})["ok"]
        ratio = "–" if failed else _fmt(r["ratio_to_newton"], ".2f")
        wall = f"{r['wall_s']:.1f} ({r['wall_min_s']:.1f}-{r['wall_max_s']:.1f}, n={r['runs']})"
        print("| " + " | ".join([
            r["twin"], f"{r['size_mm']:g}", _fmt(r.get("max_dihedral_deg"), "g"), str(r["tets"]),
            _fmt(r.get("slivers"), "d"), f"{r['c1_pa']:.0f}", r["method"],
            "yes" if r["ok"] else "**no**", _fmt(r["load_factor"], ".3g"),
            _fmt(r["iterations"], "d"), wall, ratio,
            _fmt(r["round_trip_mm"], ".2g")]) + " |")  # fmt: skip


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--twin", action="append", default=[], help="NAME=SCANS,WORK")
    p.add_argument("--table-from", type=Path, help="print the saved rows' tables (--jsonl)")
    p.add_argument("--sizes", default="8,10,12,14,16")
    p.add_argument("--methods", default="newton,spatial,mulf")
    p.add_argument("--c1-factors", default="1")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--fixed-point", action="store_true")
    p.add_argument("--postures", action="store_true",
                   help="also compare every other posture's surface with newton's")  # fmt: skip
    p.add_argument("--jsonl", type=Path, help="also append every row to this file")
    p.add_argument(
        "--max-dihedral",
        default="default",
        help="TetGen's optimisation bounds on the largest dihedral angle, degrees, "
        "comma-separated; 'default': the tetgen package's",
    )
    a = p.parse_args(argv)
    command = "python benchmarks/bench_reference.py " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )
    if a.table_from:
        saved = [json.loads(line) for line in a.table_from.read_text().splitlines() if line]
        print_header(FE, command=command, saved=f"{a.table_from}: {saved_commits(saved)}")
        print_table([r for r in saved if "method" in r and "ok" in r])
        print()
        print_postures([r for r in saved if "posture" in r])
        return
    if not a.twin:
        p.error("give at least one --twin NAME=SCANS,WORK (or --table-from)")
    prov = print_header(FE, command=command)
    logging.basicConfig(level=logging.WARNING)
    warnings.simplefilter("ignore")  # TetGen/open3d chatter; the table says what failed
    methods = a.methods.split(",") + (["fixed-point"] if a.fixed_point else [])
    bounds = [None if b == "default" else float(b) for b in a.max_dihedral.split(",")]
    rows, compared = [], []
    for spec in a.twin:
        name, paths = spec.split("=", 1)
        scans, work = (Path(x) for x in paths.split(","))
        for size, bound in itertools.product((float(s) for s in a.sizes.split(",")), bounds):
            mesh, gravity, others = reference_mesh(scans, work, size, bound)
            for factor in (float(f) for f in a.c1_factors.split(",")):
                new, cmp = bench_case(name, mesh, gravity, size, factor, methods, a.repeat,
                                      others if a.postures else None, bound)  # fmt: skip
                rows += new
                compared += cmp
                if a.jsonl:
                    with a.jsonl.open("a") as fh:
                        # each saved row names the code that measured it (review BL)
                        fh.writelines(
                            json.dumps({**r, "source": prov["source"]}) + "\n" for r in new + cmp
                        )
    print("command: " + command)
    print_table(rows)
    if compared:
        print()
        print_postures(compared)


if __name__ == "__main__":
    main()
