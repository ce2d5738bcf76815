"""Calibration benchmark: accuracy against the twin's truth, over seeds, and timings.

For each preset and seed this script synthesises the twin (the preset's hidden effects, or
``--effect`` as ``phantom-calib synth`` takes it), ingests it (timed apart: imaging, not
FE), calibrates it with the given options and validates it, and keeps one JSON per case in
``--twins DIR`` (a re-run reuses the finished cases: the matrix can be filled in several
sittings). It prints per case the model mesh's tets and size, the reference state and how
its stress-free reference was solved, c1, its 95 % interval and whether the truth lies
inside, the model-fit verdict, the optimiser's status, FE solves, ingest and calibration
wall times, and the fiducial-frame surface and tumour-centre errors per scan; then per
preset and effect the mean and spread over seeds of the relative c1 error, the interval's
coverage of the truth (with its count) and timings.

    python benchmarks/bench_calib.py [--presets quick,dissertation] [--seeds 0,1,2]
        [--effect none] [--twins DIR] [--objective surface] [--reference-state unload]
        [--mesh-size 12] [--mesh-check 1.4|1.4,0.714] [--profile 5]

The calibration tables of the README and of docs/calibration-evidence.md are printed by
it (the command is printed with them).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _provenance import FE, IMAGING, print_header, short_commit

from calib.fitting import CalibrationOptions
from calib.fitting.options import mesh_check_ratios, parse_mesh_check
from calib.model.effects import parse_effects
from calib.twin import PRESETS, synthesize
from calib.workflows.calibrate import run_calibration
from calib.workflows.ingest import run_ingest
from calib.workflows.validate import run_validation


def _case_name(preset: str, effect: str, seed: int, o: CalibrationOptions) -> str:
    tag = effect.replace("=", "").replace(":", "x").replace(",", "+") or "default"
    name = f"{preset}-{tag}-seed{seed}-{o.objective}-{o.reference_state}-{o.mesh_size_mm:g}mm"
    if o.mesh_check_ratio != CalibrationOptions.mesh_check_ratio:  # older names stay valid
        ratios = mesh_check_ratios(o.mesh_check_ratio) or (0.0,)
        name += "-check" + "+".join(f"{q:g}" for q in ratios)
    return name


def run_case(root: Path, preset: str, effect: str, seed: int, o: CalibrationOptions) -> dict:
    """One synth -> ingest -> calibrate -> validate, with the truth beside (cached JSON).

    A new case records ``source``, the commit it ran from (``calib.io.provenance``); a case
    read back from ``root`` comes with ``cached: True`` (the table marks it: it was not
    measured by this run, and may be from another commit).
    """
    name = _case_name(preset, effect, seed, o)
    record = root / f"{name}.json"
    if record.is_file():
        return {**json.loads(record.read_text()), "cached": True}
    from calib.io import provenance

    source = provenance()["source"]  # the code this case runs (review BL)
    effects = parse_effects(effect.split(",") if effect else [], default=PRESETS[preset].effects)
    twin = root / f"{preset}-{effect or 'default'}-seed{seed}"
    t0 = time.perf_counter()
    if not (twin / "truth" / "truth.json").is_file():
        synthesize(twin, preset=preset, seed=seed, effects=effects, overwrite=True)
    t_synth = time.perf_counter() - t0
    truth = json.loads((twin / "truth" / "truth.json").read_text())
    work = root / f"{name}-work"
    t0 = time.perf_counter()
    run_ingest(twin / "scans", work)
    t_ingest = time.perf_counter() - t0
    cal = run_calibration(twin / "scans", work, o)
    val = run_validation(work)
    c1_true = truth["material"]["c1_pa"]
    ci = cal["c1_ci95_pa"]
    out = {
        "case": name,
        "preset": preset,
        "effect": effect or "default",
        "seed": seed,
        "active_effects": truth["effects"]["active"],
        "c1_true_pa": c1_true,
        "c1_pa": cal["c1_pa"],
        "c1_ci95_pa": ci,
        "covered": None if ci is None else bool(ci[0] <= c1_true <= ci[1]),
        "relative_error": cal["c1_pa"] / c1_true - 1.0,
        "model_fit": cal.get("model_fit"),
        "optimiser": cal["optimiser"],
        "uncertainty_method": cal["uncertainty"]["method"],
        "mesh": cal["mesh"],
        "fe_solves": cal["fe_solves"],
        "mesh_check": cal["uncertainty"].get("mesh_check"),
        "synth_s": t_synth,
        "ingest_s": t_ingest,
        "calibration_s": cal["wall_s"],
        "reference_state": cal["reference_state"],
        "recovery": (cal.get("reference_recovery") or {}).get("method"),
        "surface_mean_mm": {
            n: s["surface_error_mm"]["fiducial"]["mean"]["value"] for n, s in val["scans"].items()
        },
        "tumour_mm": {
            n: ((s.get("tumour_error_mm") or {}).get("fiducial") or {}).get("value")
            for n, s in val["scans"].items()
        },
        "roles": {n: s["role"] for n, s in val["scans"].items()},
        "source": source,
    }
    record.write_text(json.dumps(out, indent=2) + "\n")
    return out


def _print_case(r: dict) -> None:
    ci = r["c1_ci95_pa"]
    ci_txt = f"{ci[0]:.1f}-{ci[1]:.1f}" if ci else "none"
    mf = r.get("model_fit") or {}
    fit = mf.get("verdict", "-")
    if mf.get("p_value") is not None:
        fit += f" (F p {mf['p_value']:.2g}"
        fit += f", Q p {mf['postures']['p_value']:.2g})" if mf.get("postures") else ")"
    opt = (
        "converged" if r["optimiser"]["success"] else f"NOT converged ({r['optimiser']['message']})"
    )
    surf = " / ".join(f"{v:.2f}" for v in r["surface_mean_mm"].values())
    tumour = " / ".join("–" if v is None else f"{v:.2f}" for v in r.get("tumour_mm", {}).values())
    mesh = r["mesh"]
    # a reused case is marked with the commit it was measured at (review BL)
    case = r["case"] + (
        f" (cached, commit {short_commit(r.get('source'))})" if r.get("cached") else ""
    )
    print(
        f"| {case} | {mesh['n_tets']} ({mesh['size_mm']:g} mm) | {_recovery_cell(r)} "
        f"| {r['c1_pa']:.1f} ({ci_txt}) | {100 * r['relative_error']:+.1f} % | "
        f"{'yes' if r['covered'] else 'no'} | {_mesh_check_cell(r.get('mesh_check'))} | {fit} "
        f"| {opt} | {r['fe_solves']} | {r['ingest_s']:.0f} | {r['calibration_s']:.0f} | {surf} "
        f"| {tumour or '–'} |"
    )


def _recovery_cell(r: dict) -> str:
    """How the stress-free reference was solved: ``newton`` (straight elements), ``spatial``
    (curved; ``switched`` where an unload calibration fell back to them), ``–`` (shortcut)."""
    state, method = r.get("reference_state"), r.get("recovery")
    if state is None:  # a case recorded before these were kept
        return "?"
    if method is None or state == "shortcut":  # recorded as "none (shortcut)"
        return f"{state}: –"
    return f"{state}: {method}" + (
        " (switched)" if state == "unload" and method == "spatial" else ""
    )


def _mesh_check_cell(check: dict | None) -> str:
    """The check meshes' c1 and the GCI (older records: the GCI alone, or "-")."""
    if not check:
        return "-"
    if check.get("gci_ln_c1") is None:
        return "failed"
    c1s = ", ".join(
        f"{m['mesh_size_mm']:.1f} mm {m['c1_pa']:.1f}"
        if m["c1_pa"]
        else f"{m['mesh_size_mm']:.1f} mm failed"
        for m in check.get("meshes", [])
    )
    how = check.get("convergence", "assumed order")
    if how == "observed order":
        how += f" {check['order']:.2f}"
    return f"{c1s}: GCI {100 * check['gci_ln_c1']:.2g} % ({how})"


def _summary(rows: list[dict]) -> None:
    print(
        "\n| preset | effect | seeds | c1 error mean (sd) | truth covered | model fit: misfit "
        "| calibration s median (range) |"
    )
    print("|---|---|---|---|---|---|---|")
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["preset"], r["effect"]), []).append(r)
    for (preset, effect), rs in groups.items():
        e = 100 * np.array([r["relative_error"] for r in rs])
        cov = [r["covered"] for r in rs if r["covered"] is not None]
        mis = [r for r in rs if (r.get("model_fit") or {}).get("verdict") == "misfit"]
        t = np.array([r["calibration_s"] for r in rs])
        sd = f"{e.std(ddof=1):.1f}" if len(e) > 1 else "-"
        print(
            f"| {preset} | {effect} | {len(rs)} | {e.mean():+.1f} % ({sd}) | "
            f"{sum(cov)}/{len(cov)} | {len(mis)}/{len(rs)} | {np.median(t):.0f} "
            f"({t.min():.0f}-{t.max():.0f}) |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="quick", help="comma-separated preset names")
    ap.add_argument("--seeds", default="0", help="comma-separated twin seeds")
    ap.add_argument(
        "--effect",
        default="",
        help="the twin's hidden effects as synth's --effect, comma-separated "
        "(e.g. none, skin=1.5:8, sliding); default: the preset's",
    )
    ap.add_argument("--twins", type=Path, default=None, help="folder of the twins and results")
    ap.add_argument("--objective", default="surface")
    ap.add_argument("--reference-state", default="unload")
    ap.add_argument("--mesh-size", type=float, default=CalibrationOptions.mesh_size_mm)
    ap.add_argument(
        "--mesh-check", type=parse_mesh_check, default=CalibrationOptions.mesh_check_ratio
    )
    ap.add_argument("--profile", type=int, default=CalibrationOptions.profile_points)
    args = ap.parse_args()
    options = CalibrationOptions(
        objective=args.objective,
        reference_state=args.reference_state,
        mesh_size_mm=args.mesh_size,
        mesh_check_ratio=args.mesh_check,
        profile_points=args.profile,
    )
    print_header((*FE, *IMAGING), command="python " + " ".join(shlex.quote(a) for a in sys.argv))
    print(
        "| case | model tets (size) | reference: recovery | c1 Pa (95 %) | error | truth inside "
        "| mesh check Pa | model fit | optimiser | FE solves | ingest s | calibration s "
        "| surface mean mm per scan | tumour mm per scan |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.twins or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        for preset in args.presets.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                r = run_case(root, preset, args.effect, seed, options)
                _print_case(r)
                rows.append(r)
    _summary(rows)
    cached = [r for r in rows if r.get("cached")]
    if cached:  # their times and results are not this run's (review BL)
        print(
            f"\n{len(cached)} of {len(rows)} cases reused from {args.twins} (cached): "
            "measured by an earlier run, at the commit their row names"
        )


if __name__ == "__main__":
    main()
