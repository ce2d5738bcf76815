"""Missing-effect benchmark: a seeded matrix of quick twins through synth -> calibrate -> diagnose.

Issue 13's bars: the right name in >= 90 % of effect sets; 0 false namings on null sets;
after adding the named effect c1 within 5 % of the truth (the skin twin: from ~555 back
to ~420 Pa) and the held-out posture's surface error above the noise floor cut by
>= 50 %; a detection curve over the skin ratio (1 -> 8) showing where naming starts;
<= 15 min per quick scan set on 2 cores (the diagnosis alone).

Cases (``--cases``): each library effect the twin can hide at its preset amplitude
(``skin``, ``inclusions``, ``mooney``, ``poisson``, ``density``, ``sliding``: the plate
on tangential springs of ``--sliding-springs``, default ``SLIDING_SPRINGS_PA_PER_MM``;
``inclusions`` at ``--inclusion-ratio`` times the bulk's stiffness when given) x
``--seeds`` (default 0,1,2), ``none`` x ``--null-seeds`` (default 0-4), and the
detection curve ``skin=1.5:R`` for R in ``--ratios`` (default 2,4,8; R = 1 is the null
set) at seed 0. Every case writes ``OUT/cases/<case>.json`` when done and is skipped when
that file exists, so the matrix can be run in pieces and resumed (``--only`` runs a
subset by name); a case's twin and calibration are reused when present (delete
``OUT/<case>/work`` to calibrate again). The twins' truth (``OUT/<case>/twin/truth``)
is read here only to score. The table's held-out cut is that of the mean |residual| to
the curved model surface (``diagnosis.json``'s ``gap.<scan>.cut_above_floor``), its
``noise sd`` the measured noise model's (mm).

What counts as the right name: the hidden effect named (alone or in a confounded
pair). For ``density`` (never identifiable under gravity alone: the calibration absorbs
it into c1) and ``mooney``/``sliding`` when the diagnosis reports them not identifiable
or unavailable, the right answer is that no effect is named; these cases are scored
apart and shown in the table.

    python benchmarks/bench_diagnose.py --out DIR [--cases skin,none,curve] [--seeds 0,1,2]
        [--null-seeds 0,1,2,3,4] [--ratios 2,4,8] [--only NAME,...] [--table]
        [--rim-margin MM|element] [--noise-profile flat|plate] [--mesh-error ignored|absorbed]
        [--rim-profile] [--model-error]
        [--mesh-series MM,...]
        [--mesh-size MM] [--mesh-max-dihedral DEG] [--parameter-limits]
        [--sliding-springs PA_PER_MM] [--inclusion-ratio R] [--explained-margin MM|element]
        [--inclusion-mesh MM]

``--mesh-size MM`` calibrates on that model mesh (default 14 mm, MM + 2 the retry);
``--mesh-max-dihedral DEG`` calibrates with TetGen's bound on the largest dihedral angle
(``calibrate --mesh-max-dihedral``; the diagnosis rebuilds its meshes with it).
``--rim-margin``, ``--noise-profile`` and ``--mesh-error`` diagnose with that option
(``diagnose --rim-margin``, ``--noise-profile``, ``--mesh-error``; use a fresh ``--out``,
the cases already there are skipped). ``--rim-profile`` prints, for each finished null
case, the residual of its c1-only fit with every measured point kept (rim
margin 0) by height above the back plate: the measurement behind ``--rim-margin
element`` (:func:`calib.discrepancy.problem.rim_margin_of`). ``--model-error`` prints,
for each finished effect case whose diagnosis refitted its hidden effect and whose seed
has a finished null case (``none-s<seed>``), how much of what the effect adds to the
residual over the null twin the best refit removes, beside the diagnosis' share (which
counts the model's own error above the noise floor as residual to explain;
:func:`model_error`). ``--mesh-series MM,...`` prints each finished case's c1-only fit
beyond the share's margin on model meshes of those sizes (:func:`mesh_series`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

# benchmarks/_provenance.py: on the path when run as a script, not when imported by a test
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _provenance import FE, IMAGING, print_header, saved_commits

TWIN_EFFECTS = ("skin", "inclusions", "mooney", "poisson", "density", "sliding")
#: The sliding twin's plate rides on tangential springs of this stiffness (Pa/mm): the
#: quick twin with a frictionless plate (``--effect sliding``) has no FE solution (on
#: 100 Pa/mm springs the homogeneous calibration takes c1 as -22 %). The body's own
#: shear stiffness per area of plate is about ``2 c1 / H`` = 840 Pa / 75 mm = 11 Pa/mm,
#: so 1000 Pa/mm slips little (the clamped calibration takes it as c1 -2.3 %) and
#: 300 Pa/mm more (-8 %); ``--sliding-springs`` runs another stiffness (case names
#: ``sliding-k<K>-s<seed>``).
SLIDING_SPRINGS_PA_PER_MM = 1000.0


def _cases(args) -> list[tuple[str, list[str], int, str]]:
    """``(name, --effect specs, seed, hidden effect)`` of the matrix."""
    out = []
    wanted = set(args.cases.split(","))
    seeds = [int(s) for s in args.seeds.split(",") if s]
    for eff in TWIN_EFFECTS:
        if eff in wanted or "effects" in wanted:
            spec, tag = eff, eff
            if eff == "sliding":
                k = args.sliding_springs
                spec = f"sliding={k:g}"
                tag = "sliding" if k == SLIDING_SPRINGS_PA_PER_MM else f"sliding-k{k:g}"
            if eff == "inclusions" and args.inclusion_ratio is not None:
                spec, tag = (
                    f"inclusions={args.inclusion_ratio:g}",
                    f"inclusions-r{args.inclusion_ratio:g}",
                )
            out += [(f"{tag}-s{s}", [spec], s, eff) for s in seeds]
    if "none" in wanted:
        out += [(f"none-s{s}", ["none"], s, "none") for s in map(int, args.null_seeds.split(","))]
    if "curve" in wanted:
        for r in args.ratios.split(","):
            out.append((f"skin-r{r}-s0", [f"skin=1.5:{r}"], 0, "skin"))
    if args.only:
        keep = set(args.only.split(","))
        out = [c for c in out if c[0] in keep]
    return out


def _noise_check(twin: Path, work: Path) -> dict:
    """The measured surfaces against the twin's true ones: the imaging's own error (mm)."""
    import imaging
    from calib.model.residuals import closest_on_surface

    out = {}
    for f in sorted((twin / "truth").glob("*_surface.ply")):
        name = f.name.removesuffix("_surface.ply")
        ing = work / "scans" / name / "surface.ply"
        if not ing.is_file():
            continue
        true, meas = imaging.read_ply(f), imaging.read_ply(ing)
        pts = meas.vertices_lps_mm[~np.asarray(meas.back_plate, bool)]
        c, _, _, n = closest_on_surface(true.vertices_lps_mm, true.faces, pts)
        d = np.einsum("kj,kj->k", pts - c, n)
        out[name] = {"mean_mm": float(d.mean()), "sd_mm": float(d.std()),
                     "rms_mm": float(np.sqrt(np.mean(d**2)))}  # fmt: skip
    return out


def run_case(
    root: Path,
    name: str,
    specs: list[str],
    seed: int,
    hidden: str,
    rim_margin=None,
    noise_profile: str = "flat",
    explained_margin=None,
    max_dihedral_deg=None,
    mesh_size_mm: float = 14.0,
    parameter_limits: bool = False,
    inclusion_mesh_mm: float | None = None,
    mesh_error: str = "ignored",
) -> dict:
    import fem
    from calib.discrepancy import DiagnosisError, DiagnosisOptions
    from calib.fitting import CalibrationOptions
    from calib.model.effects import parse_effects
    from calib.twin import PRESETS, synthesize
    from calib.workflows.calibrate import run_calibration
    from calib.workflows.diagnose import run_diagnosis

    case = root / name
    twin, work = case / "twin", case / "work"
    t0 = time.perf_counter()
    if not (twin / "truth" / "truth.json").is_file():
        eff = parse_effects(specs, default=PRESETS["quick"].effects)
        try:
            synthesize(twin, preset="quick", seed=seed, effects=eff, overwrite=True)
        except fem.ConvergenceError as exc:  # the twin itself has no FE solution
            return {"case": name, "specs": specs, "seed": seed, "hidden": hidden,
                    "failed": f"synth: {exc}", "synth_s": time.perf_counter() - t0}  # fmt: skip
    t1 = time.perf_counter()
    if (work / "calibration.json").is_file():  # a calibration of this case: reused
        cal = json.loads((work / "calibration.json").read_text())
    else:
        opts = CalibrationOptions(
            mesh_size_mm=mesh_size_mm,
            mesh_retry_mm=(mesh_size_mm + 2.0,),
            profile_points=0,
            mesh_max_dihedral_deg=max_dihedral_deg,
        )
        cal = run_calibration(twin / "scans", work, opts)
    t2 = time.perf_counter()
    used = (cal.get("provenance") or {}).get("parameters") or {}
    margin = {} if rim_margin is None else {"rim_margin_mm": rim_margin}
    if explained_margin is not None:
        margin["explained_margin_mm"] = explained_margin
    opts = DiagnosisOptions(
        **margin,
        noise_profile=noise_profile,
        parameter_limits=parameter_limits,
        inclusion_mesh_mm=inclusion_mesh_mm,
        mesh_error=mesh_error,
    )
    try:
        doc = run_diagnosis(work, opts)
    except DiagnosisError as exc:  # e.g. --inclusion-mesh with an inclusion at the surface
        failed = f"diagnose: {exc}"
        return {"case": name, "specs": specs, "seed": seed, "hidden": hidden, "failed": failed}
    t3 = time.perf_counter()
    truth = json.loads((twin / "truth" / "truth.json").read_text())
    c1_true = truth["material"]["c1_pa"]
    named = doc["named"] + doc["confounded_with"]
    gap = doc["gap"]
    hold = doc["scans"]["holdout"]
    return {
        "case": name,
        "specs": specs,
        "seed": seed,
        "hidden": hidden,
        "truth_effects": truth["effects"],
        "verdict": doc["verdict"],
        "named": doc["named"],
        "confounded_with": doc["confounded_with"],
        "false_naming": bool(named) and hidden not in named,
        "c1_true_pa": c1_true,
        "c1_calibrated_pa": cal["c1_pa"],
        "c1_refit_pa": doc["c1_pa"],
        "c1_refit_ci95_pa": doc["c1_ci95_pa"],
        "c1_error": doc["c1_pa"] / c1_true - 1.0,
        "holdout": hold,
        "rim_margin_mm": doc["scans"]["rim_margin_mm"],
        "explained_margin_mm": doc["scans"]["explained_margin_mm"],
        "noise_profile": doc["options"].get("noise_profile", "flat"),
        # as it ran: "absorbed", "unavailable" (asked for, not built) or "ignored"
        "mesh_error": ((doc.get("model_mesh") or {}).get("error") or {}).get("status", "ignored"),
        # the calibration's own (a reused one may differ from the options asked for)
        "mesh_max_dihedral_deg": used.get("mesh_max_dihedral_deg"),
        "mesh_size_mm": used.get("mesh_size_mm", mesh_size_mm),
        "mesh_note": doc["calibration"].get("mesh_note"),
        "inclusion_mesh_mm": inclusion_mesh_mm,
        "holdout_cut_above_floor": gap[hold].get("cut_above_floor") if hold else None,
        "holdout_before_mm": gap[hold]["surface_error_mm"]["before"]["mean"] if hold else None,
        "holdout_after_mm": gap[hold]["surface_error_mm"].get("after", {}).get("mean")
        if hold
        else None,  # fmt: skip
        "holdout_residual_mm": gap[hold].get("residual_mm") if hold else None,
        "floor_mm": doc["noise"]["floor_mean_abs_mm"],
        "noise_model": doc["noise"]["model"],
        "imaging_error": _noise_check(twin, work),
        "effects": {
            k: {kk: v.get(kk) for kk in ("status", "p_holm", "significant")}
            for k, v in doc["effects"].items()
        },  # fmt: skip
        "candidates": doc["candidates"],
        "hidden_screen": _hidden_screen(doc, hidden),
        "synth_s": t1 - t0,
        "calibrate_s": t2 - t1,
        "diagnose_s": t3 - t2,
        "diagnose_fe_solves": doc["fe_solves"],
    }


#: The profile cell's tag of a diagnosis run with ``--mesh-error absorbed``, as it ran.
_MESH_ERROR_TAG = {"absorbed": "+mesh", "unavailable": "+mesh(n/a)"}


def _expected(row: dict) -> str | None:
    """The name a right diagnosis gives: the hidden effect where the diagnosis can name it.

    None for a null set, for ``density`` (never identifiable under gravity alone) and for
    a hidden effect the diagnosis reported not identifiable or unavailable (then the
    right answer is that nothing is named).
    """
    hidden = row["hidden"]
    if hidden in ("none", "density"):
        return None
    status = (row.get("effects") or {}).get(hidden, {}).get("status")
    return hidden if status == "identifiable" else None


def _is_curve(row: dict) -> bool:
    """A detection-curve case (``skin-rR-s0``), not an effect at its preset amplitude."""
    return row["case"].startswith("skin-r")


def _at_preset(row: dict) -> bool:
    """An effect at its preset amplitude or a null set: not the curve, not another
    amplitude (``--sliding-springs``: ``sliding-kK-sS``; ``--inclusion-ratio``:
    ``inclusions-rR-sS``)."""
    return not any(tag in row["case"] for tag in ("-k", "-r"))


def _right(row: dict) -> bool:
    named = row["named"] + row["confounded_with"]
    want = _expected(row)
    return want in named if want is not None else not named


def _mesh_cell(row: dict) -> str:
    """``SIZE[/BOUND]`` of the calibration's mesh: size in mm, TetGen's dihedral bound in
    degrees when one was asked for; ``*`` when the diagnosis ran on another mesh (the
    calibration's admitted no straight stress-free reference)."""
    size = row.get("mesh_size_mm") or 14.0  # rows from before the option: 14 mm
    bound = row.get("mesh_max_dihedral_deg")
    cell = f"{size:g}" + (f"/{bound:g}" if bound else "")
    if row.get("inclusion_mesh_mm"):  # diagnose --inclusion-mesh: spheres of these elements
        cell += f"+i{row['inclusion_mesh_mm']:g}"
    return cell + ("*" if row.get("mesh_note") else "")


def _hidden_cell(row: dict) -> str:
    """The hidden effect's first-screen score t and one-step estimate with its detectable
    size (``hidden_screen``; empty for null sets and rows from before it was kept); with
    ``--parameter-limits``, ``lim`` and the size of the effect's own parameter the scans
    would show (``diagnose --parameter-limits``: inclusions and skin as the ratio to the
    bulk's c1, sliding as the springs' Pa/mm, poisson as nu; ``beyond``: not within the
    physical range)."""
    h = row.get("hidden_screen")
    if not h:
        return ""
    cell = f"{h['statistic']:.2f}, {h['estimate']:.3g} ({h['detectable']:.3g})"
    lim = h.get("parameter_limit")
    if not lim:
        return cell
    if lim["status"] == "reached":
        return cell + f" lim {lim['value']:.3g}"
    return cell + " lim " + ("beyond" if lim["status"] == "beyond the range" else "none")


def _inside_limit(row: dict) -> bool | None:
    """Whether the hidden effect's truth lies inside its limit (nearer neutral than the
    size the scans would show 4 times in 5): a miss these data explain. None without a
    reached limit (named effects have none: only what the screen did not find gets one)."""
    lim = (row.get("hidden_screen") or {}).get("parameter_limit") or {}
    truth = row.get("truth_effects") or {}
    if lim.get("status") != "reached" or not truth:
        return None
    from calib.discrepancy.limits import visible_side

    v, hidden = lim["value"], row["hidden"]
    true = {  # the truth in the limit's quantity (ParameterLimit.quantity)
        "sliding": lambda: truth["sliding_stiffness_pa_per_mm"],
        "poisson": lambda: truth["nu"],
        "skin": lambda: truth["skin_ratio"],
        "inclusions": lambda: truth["inclusion_ratio"],
        "mooney": lambda: truth["c2_pa"] / row["c1_true_pa"],
    }.get(hidden)
    if true is None:
        return None
    side = lim.get("visible") or visible_side(hidden)  # cases diagnosed before the field
    return true() < v if side == "above" else true() > v


def _physical(name: str, v: float) -> str:
    """A refitted library parameter as the quantity the README gives: the stiffness ratio
    for skin and inclusions (the parameter is the ratio - 1), the springs for sliding (ln
    k), c2/c1 for mooney, nu for poisson; a nuisance's own name and value otherwise."""
    from calib.discrepancy.refit import PHYSICAL

    if name in PHYSICAL:
        q = PHYSICAL[name]
        return f"{q.label} {q.convert(v):.3g} {q.unit}".rstrip()
    if name == "mooney":
        return f"c2/c1 {v:.3g}"
    if name == "poisson":
        return f"nu {v:.4g}"
    return f"{name} {v:.3g}"


def _detail_lines(rows: list[dict]) -> list[str]:
    """Per effect set: the hidden effect's screen (t, se, Holm p: ``hidden_screen``) and
    every refitted candidate (its physical parameters, the share of the residual above the
    floor it explains, named or why not: ``candidates``), as kept in ``cases/<case>.json``."""
    out = []
    for r in rows:
        h = r.get("hidden_screen")
        if r["hidden"] == "none" or _is_curve(r) or not (h or r.get("candidates")):
            continue
        screen = "no screen column"
        if h:
            screen = (
                f"t {h['statistic']:.2f}, se {h['standard_error']:.3g}, Holm p {h['p_holm']:.2g}"
            )
        refits = []
        for c in r.get("candidates") or []:
            params = ", ".join(
                _physical(n, v)
                for n, v in (c.get("parameters") or {}).items()
                if "[" not in n  # per-scan nuisances: their names carry the scan
            )
            share = c.get("explained")
            if not c.get("passes"):
                what = c.get("reason") or "not named"
            elif c["effect"] in r["named"] or c["effect"] in r["confounded_with"]:
                what = "named"
            else:
                what = "passes, not named"
            refits.append(
                f"{c['effect']}{' ' + params if params else ''}"
                + ("" if share is None else f", explains {100 * share:.0f} %")
                + f" ({what})"
            )
        out.append(
            f"{r['case']}: {r['hidden']} screen {screen}; refits: "
            + ("; ".join(refits) if refits else "none")
        )
    return out


def _table(rows: list[dict]) -> None:
    failed = [r for r in rows if r.get("failed")]
    rows = [r for r in rows if not r.get("failed")]
    head = (
        "case",
        "verdict",
        "expect",
        "right",
        "c1 cal",
        "c1 refit",
        "err %",
        "hold cut",
        "noise sd",
        "diag s",
        "rim mm",
        "(d) mm",
        "profile",
        "mesh",
        "hidden t, est (detectable)",
    )
    widths = (-16, -34, 10, 5, 7, 8, 6, 8, 8, 7, 6, 6, 7, -7, -26)  # negative: left-aligned

    def line(cells) -> str:
        return " ".join(
            f"{c:<{-w}s}" if w < 0 else f"{c:>{w}s}" for c, w in zip(cells, widths, strict=True)
        )

    print(line(head))
    for r in rows:
        # no cut without a named effect ("after" is c1 alone refitted; cases diagnosed
        # before diagnosis.json said so carry one)
        cut = r["holdout_cut_above_floor"] if r["named"] else None
        judged = r.get("explained_margin_mm")  # rows from before 2026-12: every point
        cells = (
            r["case"],
            r["verdict"][:34],
            _expected(r) or "no name",
            "yes" if _right(r) else "NO",
            f"{r['c1_calibrated_pa']:.1f}",
            f"{r['c1_refit_pa']:.1f}",
            f"{100 * r['c1_error']:+.1f}",
            "" if cut is None else f"{100 * cut:.0f} %",
            f"{r['noise_model']['sigma_mm']:.3f}",
            f"{r['diagnose_s']:.0f}",
            f"{r.get('rim_margin_mm', 5.0):g}",
            "-" if judged is None else f"{judged:.3g}",
            r.get("noise_profile", "flat") + _MESH_ERROR_TAG.get(r.get("mesh_error"), ""),
            _mesh_cell(r),
            _hidden_cell(r),
        )
        print(line(cells))
    for r in failed:
        print(f"{r['case']:16s} FAILED {r['failed'][:100]}")
    preset = [r for r in rows if _at_preset(r)]  # the bars: effects at preset amplitude
    other = [r for r in rows if not _at_preset(r) and not _is_curve(r)]
    eff = [r for r in preset if _expected(r) is not None]
    apart = [r for r in preset if r["hidden"] != "none" and _expected(r) is None]
    null = [r for r in rows if r["hidden"] == "none"]
    named_ok = [r for r in eff if _right(r)]
    print()
    if eff:
        print(f"right name: {len(named_ok)}/{len(eff)} effect sets (bar >= 90 %)")
    if other:
        which = ", ".join(f"{r['case']} {'yes' if _right(r) else 'no'}" for r in other)
        n_right = sum(map(_right, other))
        print(f"right name at other amplitudes (not in the bars): {n_right}/{len(other)} ({which})")
    if apart:
        print(
            f"hidden effects the diagnosis cannot name (density, not identifiable, "
            f"unavailable): nothing named in {sum(_right(r) for r in apart)}/{len(apart)}"
        )
    if failed:
        print(f"cases without a result (the twin or a step failed): {len(failed)}")
    if null:
        print(f"false namings on null sets: {sum(bool(r['named']) for r in null)}/{len(null)} "
              "(bar 0)")  # fmt: skip
        quiet = sum(r["verdict"] == "no missing effect" for r in null)
        print(f"null sets answering 'no missing effect': {quiet}/{len(null)}")
    if named_ok:
        within = sum(abs(r["c1_error"]) <= 0.05 for r in named_ok)
        print(f"c1 within 5 % of the truth after naming: {within}/{len(named_ok)}")
        cuts = [r["holdout_cut_above_floor"] for r in named_ok
                if r["holdout_cut_above_floor"] is not None]  # fmt: skip
        print(f"held-out error above the floor cut >= 50 %: {sum(c >= 0.5 for c in cuts)}/"
              f"{len(cuts)}")  # fmt: skip
    limited = [(r, _inside_limit(r)) for r in rows]
    limited = [(r, inside) for r, inside in limited if inside is not None]
    if limited:
        inside = [r["case"] for r, i in limited if i]
        which = f" ({', '.join(inside)})" if inside else ""
        head = "hidden effects not found whose truth lies inside their limit"
        print(f"{head} (--parameter-limits): {len(inside)}/{len(limited)}{which}")
    if rows:
        t = [r["diagnose_s"] for r in rows]
        print(f"diagnose wall time: median {np.median(t):.0f} s, max {max(t):.0f} s "
              "(bar <= 900 s)")  # fmt: skip
    curve = sorted((r for r in rows if _is_curve(r)), key=lambda r: float(r["specs"][0][9:]))
    if curve:
        print("detection curve (skin 1.5 mm, seed 0): "
              + ", ".join(f"ratio {r['specs'][0][9:]}: {r['verdict']}" for r in curve))  # fmt: skip
    details = _detail_lines(rows)
    if details:
        print()
        print("hidden effect's screen and the refits, per effect set (cases/<case>.json):")
        for d in details:
            print("  " + d)


def rim_profile(work: Path) -> list[tuple[str, list[tuple[int, float]]]]:
    """Per diagnosis scan, ``(points, rms mm)`` of the c1-only fit's residual per height band.

    The residual is centred by its mean beyond 20 mm (a scan's offset is a nuisance).
    """
    from calib.data import read_work
    from calib.discrepancy.problem import build_problem, plate_height_mm
    from calib.discrepancy.refit import refit
    from calib.stats.profile import HEIGHT_BANDS_MM

    wf = read_work(work)
    prob = build_problem(wf, rim_margin_mm=0.0)
    null = refit(prob, (), screened=(), say=lambda m: None)
    out = []
    for n in prob.scans:
        height = plate_height_mm(prob.measurement(n), prob.points[n])
        r = null.fields.residual[n]
        r = r - r[height >= 20.0].mean()
        bands = []
        for lo, hi in zip(HEIGHT_BANDS_MM[:-1], HEIGHT_BANDS_MM[1:], strict=True):
            sel = (height >= lo) & (height < hi)
            bands.append((int(sel.sum()), float(np.sqrt(np.mean(r[sel] ** 2)))))
        out.append((n, bands))
    return out


def _judged_ms(
    work: Path,
    like: dict,
    states: list,
    *,
    mesh_size_mm: float | None = None,
    inclusion_mesh_mm: float | None = None,
) -> dict:
    """Mean squares beyond the share's margin (each scan's mean removed) of model states.

    The diagnosis problem of ``work`` is built with the options of the diagnosis ``like``
    (a ``diagnosis.json``: its held-out scan, rim margin, mesh options and the margin
    beyond which it judged the share explained), so that an effect twin and the null twin
    of its seed are read on the same points criterion. Each of ``states`` is None (the
    c1-only fit, refitted; first), ``(c1 Pa, {effect: parameter})`` (re-solved by the FE
    model) or an effect's name (refitted jointly with c1 from the c1-only fit).
    ``mesh_size_mm``, ``inclusion_mesh_mm``: that model mesh instead (``diagnose
    --mesh-size``, ``--inclusion-mesh``).
    """
    from types import SimpleNamespace

    from calib.data import read_work
    from calib.discrepancy.diagnose import _centred_ms, _judged_points, _scan_regions
    from calib.discrepancy.problem import build_problem
    from calib.discrepancy.refit import refit
    from calib.model.effects import LIBRARY

    opt, sc = like["options"], like["scans"]
    prob = build_problem(
        read_work(work),
        holdout=sc["holdout"] or "none",
        rim_margin_mm=sc["rim_margin_mm"],
        mesh_size_mm=mesh_size_mm or opt.get("mesh_size_mm"),
        inclusion_mesh_mm=inclusion_mesh_mm or opt.get("inclusion_mesh_mm"),
    )
    margin, judged = _judged_points(prob, sc["explained_margin_mm"])
    labels = {  # per part kind, each judged point's part
        "region": {n: _scan_regions(prob, n, prob.points[n])[judged[n]] for n in prob.scans},
        "height": {n: _height_band(prob, n, judged[n], margin) for n in prob.scans},
    }
    fits, null = [], None
    for at in states:
        if at is None or isinstance(at, str):
            start = None if null is None else null.theta
            fit = refit(prob, () if at is None else (at,), say=lambda m: None, theta0=start)
            null = fit if at is None else null
            c1, res = fit.c1_pa, fit.fields.residual
            params = {n: fit.parameter(n) for n in fit.names[1:]}
        else:
            (c1, params), values = at, prob.base
            for name, v in params.items():
                values = LIBRARY[name].set(values, v)
            states_ = prob.solve(float(np.log(c1)), values, prob.scans, gradient=False)
            res = {n: prob.residuals(n, states_[n].positions_mm, None, None).r for n in prob.scans}
        ms = _centred_ms(SimpleNamespace(residual=res), judged)
        parts = _ms_by_part(res, judged, labels)
        fits.append({"c1_pa": c1, "parameters": params, "ms_mm2": ms, "parts": parts})
    return {"fits": fits, "margin_mm": margin, "mesh_size_mm": prob.mesh_size_mm}


#: Height bands above the back plate (mm) of --model-error's parts, beyond the margin.
PART_HEIGHTS_MM = (20.0, 30.0, 45.0)


def _height_band(prob, name: str, keep: np.ndarray, margin_mm: float) -> np.ndarray:
    """Each judged point's band of height above its scan's back plate (from the margin
    up, :data:`PART_HEIGHTS_MM`), as a label."""
    from calib.discrepancy.problem import plate_height_mm

    h = plate_height_mm(prob.measurement(name), prob.points[name][keep])
    edges = [e for e in PART_HEIGHTS_MM if e > margin_mm]
    lows = [margin_mm, *edges]
    names = [f"{a:g}-{b:g} mm" for a, b in zip(lows[:-1], edges, strict=True)]
    names.append(f">{lows[-1]:g} mm")
    return np.array(names)[np.searchsorted(edges, h, side="right")]


def _ms_by_part(res: dict, judged: dict, labels: dict) -> dict:
    """A fit's centred mean squares by scan and by each labelling's parts (pooled).

    Each scan's residual less its mean over the judged points, as the share's mean
    square (:func:`calib.discrepancy.diagnose._centred_ms`); ``labels`` maps a kind
    ("region", "height") to each scan's labels of those points. Returns
    ``{"scan NAME" | "KIND PART": (mm^2, points)}``.
    """
    centred = {n: r[judged[n]] - r[judged[n]].mean() for n, r in res.items()}
    out = {f"scan {n}": (float(np.mean(c**2)), len(c)) for n, c in centred.items()}
    sq = np.concatenate(list(centred.values())) ** 2
    for kind, of in labels.items():
        lab = np.concatenate([of[n] for n in centred])
        for g in sorted(set(lab)):
            out[f"{kind} {g}"] = (float(np.mean(sq[lab == g])), int(np.sum(lab == g)))
    return out


def model_error(root: Path, row: dict, inclusion_mesh_mm: float | None = None) -> dict | None:
    """How much of what a hidden effect adds the best refit of it removes, beyond the margin.

    For an effect case whose diagnosis refitted its hidden effect, with a null case of the
    same seed under ``root``: the mean squares beyond the margin the share was judged on
    (:func:`_judged_ms`) of the c1-only fit (``before``), of that refit re-solved
    (``after``), and of the null twin's c1-only fit on the same points criterion
    (``null``; on a mesh of the effect case's size where its own differs). The diagnosis'
    share is ``(before - after) / (before - floor)``, the floor the short-range noise
    (``diagnosis.json``); ``(before - after) / (before - null)`` is the share of what the
    effect adds over the null twin, whose residual above the floor is the model's own
    error (mesh, reference surface), which no library effect removes. With
    ``inclusion_mesh_mm`` both twins are read on a model mesh with their segmented
    inclusions meshed as spheres of that size, the hidden effect refitted there (the
    diagnosis' share is then not recomputed: ``share`` is that refit's against the
    diagnosis' floor). None where there is no such refit or null case.
    """
    from calib.discrepancy.problem import calibration_mesh_mm

    work = root / row["case"] / "work"
    null_work = root / f"none-s{row['seed']}" / "work"
    doc = json.loads((work / "diagnosis.json").read_text())
    cands = [  # refitted from the c1-only fit (round 1): "before" is that fit
        c
        for c in doc["candidates"]
        if c["effect"] == row["hidden"] and c["parameters"] and c["round"] == 1
    ]
    if not cands or not (null_work / "calibration.json").is_file():
        return None
    best = max(cands, key=lambda c: c["explained"])
    if inclusion_mesh_mm is None:
        own = _judged_ms(work, doc, [None, (best["c1_pa"], best["parameters"])])
    else:  # the calibration's size, else its next (build_problem), as the diagnosis does
        own = _judged_ms(work, doc, [None, row["hidden"]], inclusion_mesh_mm=inclusion_mesh_mm)
        best = {**own["fits"][1], "explained": float("nan")}
    size, im = own["mesh_size_mm"], {"inclusion_mesh_mm": inclusion_mesh_mm}
    # the null twin on the same size: its calibration's mesh where that is the size
    record = json.loads((null_work / "calibration.json").read_text())
    own_mesh = inclusion_mesh_mm is None and calibration_mesh_mm(record) == size
    null = _judged_ms(null_work, doc, [None], mesh_size_mm=None if own_mesh else size, **im)
    if null["mesh_size_mm"] != size:  # its own mesh's recovery gave way to another size
        null = _judged_ms(null_work, doc, [None], mesh_size_mm=size, **im)
    floor = float(doc["noise"]["explained_floor_rms_mm"]) ** 2
    b, a = own["fits"][0]["ms_mm2"], own["fits"][1]["ms_mm2"]
    n = null["fits"][0]["ms_mm2"]
    return {
        "case": row["case"],
        "candidate": best,
        "mesh_size_mm": size,
        "margin_mm": own["margin_mm"],
        "null_mesh_size_mm": null["mesh_size_mm"],
        "ms_mm2": {"before": b, "after": a, "null": n, "floor": floor},
        "share": (b - a) / (b - floor),
        "share_of_added": (b - a) / (b - n) if b > n else float("nan"),
        "parts": _parts(own["fits"][0]["parts"], own["fits"][1]["parts"], null["fits"][0]["parts"]),
    }


def mesh_series(
    root: Path, row: dict, sizes_mm, inclusion_mesh_mm: float | None = None
) -> list[dict]:
    """The c1-only fit of a finished case on each model mesh size, beyond the share's margin.

    On the diagnosis' own problem and points (:func:`_judged_ms`, its ``diagnosis.json``;
    the plain model mesh, or with ``inclusion_mesh_mm`` its segmented inclusions meshed
    as spheres) the c1-only fit is made on a mesh of each of ``sizes_mm``. Each row: the
    size asked for and the one used, c1 (Pa), the mean square beyond the margin and by
    scan (mm^2), the diagnosis' floor (mm^2), or ``failed`` (why: no straight
    stress-free reference on that size). What a finer mesh removes is the model's own
    error, not a missing effect; on the quick twins that error is not steady in the mesh
    size and the finer meshes lack a straight reference (README), so no rate can be
    read from such a series to count it out.
    """
    from calib.discrepancy.problem import DiagnosisError

    work = root / row["case"] / "work"
    like = json.loads((work / "diagnosis.json").read_text())
    like["options"] = {**like["options"], "inclusion_mesh_mm": inclusion_mesh_mm}
    floor = float(like["noise"]["explained_floor_rms_mm"]) ** 2
    out = []
    for size in sizes_mm:
        try:
            m = _judged_ms(work, like, [None], mesh_size_mm=float(size))
        except DiagnosisError as exc:  # no straight stress-free reference at this size
            out.append({"size_mm": float(size), "failed": str(exc)})
            continue
        fit = m["fits"][0]
        scans = {k[5:]: v[0] for k, v in fit["parts"].items() if k.startswith("scan ")}
        out.append(
            {
                "size_mm": float(size),
                "mesh_size_mm": m["mesh_size_mm"],
                "c1_pa": fit["c1_pa"],
                "ms_mm2": fit["ms_mm2"],
                "scans_ms_mm2": scans,
                "floor_ms_mm2": floor,
            }
        )
    return out


def _mesh_series_table(root: Path, rows: list, sizes_mm, inclusion_mesh_mm) -> None:
    print(
        "c1-only fit on each model mesh size, beyond the share's margin: c1, rms, the "
        "excess above the diagnosis' noise floor (sqrt(ms - floor^2)) and rms by scan (mm)"
    )
    print(f"{'case':22s} {'mesh':>5s} {'c1 Pa':>7s} {'rms':>7s} {'excess':>7s}  by scan")
    for row in rows:
        if row.get("failed"):
            continue
        if not (root / row["case"] / "work" / "diagnosis.json").is_file():
            print(f"{row['case']:22s} no diagnosis: {root / row['case'] / 'work'}")
            continue
        for r in mesh_series(root, row, sizes_mm, inclusion_mesh_mm):
            if "failed" in r:
                why = r["failed"].split(": ", 1)[-1].split(" (")[0]  # without the path, the detail
                print(f"{row['case']:22s} {r['size_mm']:5g} {why}")
                continue
            excess = np.sqrt(max(r["ms_mm2"] - r["floor_ms_mm2"], 0.0))
            scans = " ".join(f"{n} {np.sqrt(v):.4f}" for n, v in r["scans_ms_mm2"].items())
            rms = np.sqrt(r["ms_mm2"])
            head = f"{row['case']:22s} {r['mesh_size_mm']:5g} {r['c1_pa']:7.1f} {rms:7.4f}"
            print(f"{head} {excess:7.4f}  {scans}", flush=True)


def _parts(before: dict, after: dict, null: dict) -> dict:
    """Per part (:func:`_ms_by_part`): mean squares before, after and of the null twin
    (mm^2), the effect case's point count, and the share of what the effect adds there."""
    out = {}
    for part, (b, k) in before.items():
        a, n = after[part][0], null.get(part, (float("nan"), 0))[0]
        added = (b - a) / (b - n) if b > n else float("nan")
        out[part] = {"before": b, "after": a, "null": n, "n": k, "of_added": added}
    return out


def _model_error_table(root: Path, rows: list[dict], inclusion_mesh_mm: float | None) -> None:
    print(
        "beyond the share's margin: rms (mm) of the c1-only fit, of the best refit of the "
        "hidden effect, of the null twin of the same seed, and the noise floor; the share "
        "explained (diagnosis.json, recomputed) and the share of what the effect adds over "
        "the null twin"
    )
    print(
        f"{'case':22s} {'mesh':>5s} {'margin':>6s} {'refit':>18s} {'before':>7s} {'after':>7s} "
        f"{'null':>7s} {'floor':>7s} {'share':>13s} {'of added':>8s}"
    )
    from calib.discrepancy import DiagnosisError

    for r in rows:
        if r["hidden"] == "none" or r.get("failed"):
            continue
        try:
            m = model_error(root, r, inclusion_mesh_mm)
        except DiagnosisError as exc:
            print(f"{r['case']:22s} no model: {exc}", flush=True)
            continue
        if m is None:
            continue
        c = m["candidate"]
        refit_s = ", ".join(f"{k} {v:.3g}" for k, v in c["parameters"].items())
        rms = " ".join(f"{np.sqrt(v):7.4f}" for v in m["ms_mm2"].values())
        same = m["mesh_size_mm"] == m["null_mesh_size_mm"]
        told = "     –" if np.isnan(c["explained"]) else f"{c['explained']:6.0%}"
        print(
            f"{m['case']:22s} {m['mesh_size_mm']:5.3g} {m['margin_mm']:6.3g} {refit_s:>18s} "
            f"{rms} {told} {m['share']:6.0%} {m['share_of_added']:8.0%}"
            + ("" if same else "  (null twin on another mesh)"),
            flush=True,
        )
        for part, v in m["parts"].items():  # where the effect's print and the refit's differ
            rms = " ".join(f"{np.sqrt(v[k]):7.4f}" for k in ("before", "after", "null"))
            added = "     –" if np.isnan(v["of_added"]) else f"{v['of_added']:8.0%}"
            print(f"  {part:39s} {v['n']:6d} {rms} {'':29s} {added}", flush=True)


def _rim_table(root: Path, rows: list[dict]) -> None:
    from calib.stats.profile import HEIGHT_BANDS_MM  # the bands of --noise-profile plate

    edges = zip(HEIGHT_BANDS_MM[:-1], HEIGHT_BANDS_MM[1:], strict=True)
    head = " ".join(f"{f'{lo:g}-{hi:g}':>12s}" for lo, hi in edges)
    print("residual rms (mm) of the c1-only fit by height above the back plate (mm), null sets")
    print(f"{'case':10s} {'scan':14s} {head}")
    for r in rows:
        if r["hidden"] != "none" or r.get("failed"):
            continue
        for scan, bands in rim_profile(root / r["case"] / "work"):
            cells = " ".join(f"{rms:6.3f} ({k:4d})" for k, rms in bands)
            print(f"{r['case']:10s} {scan:14s} {cells}", flush=True)


def _hidden_screen(doc: dict, hidden: str) -> dict | None:
    """The first screen's column of the hidden effect with the smallest p: its score t,
    one-step estimate, se, the size it finds with 80 % power (``detectable``), Holm p."""
    cols = doc["screening"]["columns"]
    cols = [c for c in cols if c["effect"] == hidden and c.get("p_value") is not None]
    if not cols:
        return None
    best = min(cols, key=lambda c: c["p_value"])
    keys = ("name", "statistic", "estimate", "standard_error", "detectable", "p_value", "p_holm")
    out = {k: best.get(k) for k in keys}
    out["parameter_limit"] = (doc["effects"].get(hidden) or {}).get("parameter_limit")
    return out


def _numbers(ap: argparse.ArgumentParser, flag: str, text: str, kind: type) -> list:
    """A comma list of numbers as typed (``flag``), else argparse's error (exit 2)."""
    try:
        return [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        ap.error(f"{flag} takes a comma list of {kind.__name__}s, as 0,1,2; got {text!r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="folder of the twins and results")
    ap.add_argument(
        "--cases",
        default="effects,none,curve",
        help="comma list: effects (all), skin, inclusions, ..., none, curve",
    )
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--null-seeds", default="0,1,2,3,4")
    ap.add_argument("--ratios", default="2,4,8")
    ap.add_argument(
        "--only", default="", help="run (with --model-error: read) only these case names"
    )
    ap.add_argument(
        "--sliding-springs",
        type=float,
        default=SLIDING_SPRINGS_PA_PER_MM,
        help="the sliding twin's tangential springs, Pa/mm (> 0: frictionless has no solution)",
    )
    ap.add_argument(
        "--inclusion-ratio",
        type=float,
        default=None,
        help="the inclusions twin's stiffness ratio to the bulk (default: the preset's; "
        "case names inclusions-r<R>-s<seed>)",
    )
    ap.add_argument("--table", action="store_true", help="print the table of the finished cases")
    ap.add_argument(
        "--noise-profile",
        choices=("flat", "plate"),
        default="flat",
        help="diagnose with this noise profile (diagnose --noise-profile)",
    )
    ap.add_argument(
        "--mesh-error",
        choices=("ignored", "absorbed"),
        default="ignored",
        help="diagnose with the model mesh's own error ignored or absorbed (diagnose --mesh-error)",
    )
    ap.add_argument(
        "--rim-margin",
        default=None,
        help="diagnose with this rim margin (mm, or 'element'; default: diagnose's)",
    )
    ap.add_argument(
        "--explained-margin",
        default=None,
        help="judge the share explained beyond this distance from the plate (mm, or "
        "'element'; default: diagnose's; 0: every diagnosed point, the rule before 2026-12)",
    )
    ap.add_argument(
        "--mesh-size",
        type=float,
        default=14.0,
        metavar="MM",
        help="calibrate on this model mesh size, with MM + 2 as the retry (default 14)",
    )
    ap.add_argument(
        "--mesh-max-dihedral",
        type=float,
        default=None,
        metavar="DEG",
        help="calibrate with this TetGen bound on the largest dihedral angle "
        "(calibrate --mesh-max-dihedral; default: TetGen's)",
    )
    ap.add_argument(
        "--parameter-limits",
        action="store_true",
        help="diagnose with --parameter-limits (the table's 'lim': the hidden effect's "
        "detectable size in its own parameter)",
    )
    ap.add_argument(
        "--inclusion-mesh",
        type=float,
        default=None,
        metavar="MM",
        help="diagnose with the segmented inclusions meshed as spheres of MM elements "
        "(diagnose --inclusion-mesh)",
    )
    ap.add_argument(
        "--model-error",
        action="store_true",
        help="print, for each finished effect case with a null case of its seed, how much "
        "of what the hidden effect adds its best refit removes (FE re-solves; with "
        "--inclusion-mesh MM both twins on that mesh, the hidden effect refitted there)",
    )
    ap.add_argument(
        "--mesh-series",
        default="",
        metavar="MM,...",
        help="print each finished case's c1-only fit (beyond the share's margin) on model "
        "meshes of these sizes (with --inclusion-mesh MM its inclusions meshed as spheres)",
    )
    ap.add_argument(
        "--rim-profile",
        action="store_true",
        help="print the null cases' residual by height above the back plate (c1-only fits)",
    )
    args = ap.parse_args()
    # every argument is checked before OUT is touched
    if not args.sliding_springs > 0:
        ap.error(f"--sliding-springs must be > 0 Pa/mm, got {args.sliding_springs:g}")
    if args.inclusion_ratio is not None and not args.inclusion_ratio > 0:
        ap.error(f"--inclusion-ratio must be > 0, got {args.inclusion_ratio:g}")
    sizes = _numbers(ap, "--mesh-series", args.mesh_series, float) if args.mesh_series else []
    known = ["effects", "none", "curve", *TWIN_EFFECTS]
    unknown = sorted(set(args.cases.split(",")) - set(known))
    if unknown:
        ap.error(f"--cases: unknown {', '.join(unknown)}; known: {', '.join(known)}")
    _numbers(ap, "--seeds", args.seeds, int)
    _numbers(ap, "--null-seeds", args.null_seeds, int)
    _numbers(ap, "--ratios", args.ratios, float)
    from calib.discrepancy import DiagnosisError
    from calib.discrepancy.problem import parse_rim_margin

    try:
        margin = None if args.rim_margin is None else parse_rim_margin(args.rim_margin)
        explained = (
            None
            if args.explained_margin is None
            else parse_rim_margin(args.explained_margin, "--explained-margin")
        )
    except DiagnosisError as exc:
        ap.error(str(exc))
    store = args.out / "cases"
    reads = args.rim_profile or args.model_error or args.table or (sizes and not args.only)
    if reads and not store.is_dir():
        ap.error(f"{store} does not exist: run the matrix into --out first")
    if sizes and args.only and not args.out.is_dir():
        ap.error(f"--out {args.out} does not exist (--mesh-series --only reads case folders there)")
    saved = None
    if args.table:  # the table only: every row was measured by an earlier run
        saved = f"{store}/*.json: " + saved_commits(
            json.loads(p.read_text()) for p in sorted(store.glob("*.json"))
        )
    prov = print_header((*FE, *IMAGING), command=" ".join([sys.executable, *sys.argv]), saved=saved)
    if not (reads or sizes):  # the matrix: its results go to OUT/cases
        store.mkdir(parents=True, exist_ok=True)
    if args.rim_profile:
        _rim_table(args.out, [json.loads(p.read_text()) for p in sorted(store.glob("*.json"))])
        return
    if sizes:  # --only: any case folder with a diagnosis, in that order
        if args.only:
            rows = [{"case": n} for n in args.only.split(",")]
        else:
            rows = [json.loads(p.read_text()) for p in sorted(store.glob("*.json"))]
        _mesh_series_table(args.out, rows, sizes, args.inclusion_mesh)
        return
    if args.model_error:
        rows = [json.loads(p.read_text()) for p in sorted(store.glob("*.json"))]
        keep = set(args.only.split(",")) if args.only else None
        rows = [r for r in rows if keep is None or r["case"] in keep]
        _model_error_table(args.out, rows, args.inclusion_mesh)
        return
    ran = set()  # the cases this run ran (the table also shows the earlier ones)
    if not args.table:
        for name, specs, seed, hidden in _cases(args):
            path = store / f"{name}.json"
            if path.is_file():
                continue
            ran.add(name)
            print(f"case {name}: synth -> calibrate -> diagnose", flush=True)
            row = run_case(
                args.out,
                name,
                specs,
                seed,
                hidden,
                margin,
                args.noise_profile,
                explained,
                args.mesh_max_dihedral,
                args.mesh_size,
                args.parameter_limits,
                args.inclusion_mesh,
                args.mesh_error,
            )
            row["source"] = prov["source"]  # the code this case ran (review BL)
            path.write_text(json.dumps(row, indent=1))
            if row.get("failed"):
                print(f"  FAILED {row['failed']}", flush=True)
                continue
            print(f"  {row['verdict']}; c1 {row['c1_refit_pa']:.1f} Pa; "
                  f"{row['diagnose_s']:.0f} s", flush=True)  # fmt: skip
    rows = [json.loads(p.read_text()) for p in sorted(store.glob("*.json"))]
    earlier = [r for r in rows if r.get("case") not in ran]
    if earlier and not args.table:  # finished cases read back, not run again (review BL)
        print(f"{len(earlier)} of {len(rows)} cases below were run earlier, not by this run: "
              f"{saved_commits(earlier)}")  # fmt: skip
    _table(rows)


if __name__ == "__main__":
    main()
