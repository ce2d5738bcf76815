"""Text tables of calibration results (what the CLI prints)."""

from __future__ import annotations

import math

from ..fitting.meshcheck import describe_mesh_check
from ..fitting.result import no_interval_said, reference_state_said
from ..fitting.uncertainty import GAUSS_NEWTON_COVERAGE
from ..stats.noise import SMOOTH_TAKEN_FOR_NOISE

#: What validate's posture angle is (review AX: ingest's is another, 3-D, to the reference
#: scan's gravity); the console table and the report say it alike.
POSTURE_NOTE = (
    "the angle of the scan's registered gravity within its posture plane (transverse: 0° "
    "left lateral; ingest's table gives its 3-D angle to the reference scan's gravity)"
)

__all__ = ["format_calibration", "format_validation"]


def _uncertainty_lines(unc: dict, objective: str) -> list[str]:
    lines = []
    if objective == "surface" and unc.get("method") == "gauss-newton":
        lines.append(
            "  WARNING: the Gauss-Newton interval, not the series one (too few residuals, "
            f"or its noise model failed): {GAUSS_NEWTON_COVERAGE}, and there is no "
            "model-misfit test"
        )
    check = unc.get("mesh_check")
    if unc.get("c1_ci95_pa") is None:
        return lines
    if not check:
        return [*lines, "  the interval covers the residuals' noise only (no mesh check)"]
    lo, hi = unc["c1_ci95_pa"]
    found, how = describe_mesh_check(check)
    lines.append(f"  noise alone: {lo:.1f} - {hi:.1f} Pa; mesh check: {found}")
    if check.get("gci_ln_c1") is None:  # review BN: said nowhere but in that line
        lines.append(
            "  WARNING: no mesh check solved: the interval covers the residuals' noise only, "
            "not the mesh's discretisation error, and may miss c1"
        )
    if check.get("gci_ln_c1") is not None:
        lines.append(f"  discretisation bound (GCI) {100 * check['gci_ln_c1']:.2g} % ({how})")
    if check.get("convergence", "assumed order") == "assumed order" and check.get("gci_ln_c1"):
        lines.append(
            "  note: the bound assumes the FE's order (1.6); --mesh-check 1.4,0.714 observes "
            "it on a coarser and a finer mesh (the finer one costs most)"
        )
    if check.get("convergence") == "not asymptotic":
        lines.append(
            "  WARNING: c1 does not converge regularly over the check meshes: the bound is "
            "3x their spread; a finer model mesh (--mesh-size) would narrow it"
        )
    return lines


def _optimiser_lines(opt: dict | None) -> list[str]:
    if not opt:
        return []
    lines = []
    if not opt["success"]:
        lines.append(f"  WARNING: the optimiser did not converge: {opt['message']}")
    if opt.get("bound"):
        lines.append(
            f"  WARNING: c1 ended on the {opt['bound']} bound of its search range "
            "(x/÷ 4 around the first estimate)"
        )
    if opt.get("failed_evaluations"):
        lines.append(
            f"  {opt['failed_evaluations']} of {opt['evaluations']} evaluations had no FE solution"
        )
    if opt.get("replaced"):
        r = opt["replaced"]
        lines.append(
            f"  fitted again on curved stress-free elements: the straight ones had no solution "
            f"at c1 = {r['unsolved_c1_pa']:.1f} Pa (their fit stopped at {r['c1_pa']:.1f} Pa "
            f"after {r['evaluations']} evaluations)"
        )
    if opt.get("abandoned"):
        a = opt["abandoned"]
        lines.append(
            f"  tried again on curved stress-free elements, no solution at the first estimate "
            f"({a['fe_solves']} FE solves): the straight fit stands"
        )
    return lines


def _own_c1(theta) -> str:
    """A scan's own c1 from its ln c1; none where it is not a number or out of range."""
    if theta is None or not math.isfinite(theta) or abs(theta) > 50.0:  # e^50 Pa
        return "no c1 of its own"
    return f"{math.exp(theta):.0f} Pa"


def _model_fit_lines(fit: dict | None, recovery: dict | None) -> list[str]:
    lines = []
    if fit and fit.get("p_value") is not None:
        band = fit.get("band_f_verdict", fit.get("verdict"))
        what = "large-scale structure" if band == "misfit" else "no structure"
        lines.append(f"  band-F misfit test: p = {fit['p_value']:.2g} ({what} beyond the noise)")
        if band != "misfit" and (fit.get("noise") or {}).get("length_at_bound"):
            lines.append(
                "    its noise model's correlation length ended at the search bound: "
                f"{SMOOTH_TAKEN_FOR_NOISE}"
            )
    postures = (fit or {}).get("postures")
    if postures:
        own = ", ".join(f"{name} {_own_c1(s['theta'])}" for name, s in postures["scans"].items())
        lines.append(
            f"  posture consistency: Cochran Q p = {postures['p_value']:.2g} "
            f"({postures['verdict']}; each scan alone: {own})"
        )
    if fit and fit.get("verdict") == "misfit":
        lines.append(
            "  WARNING: model misfit: the interval covers noise and mesh, not this model "
            "error; it is the interval of an effective c1 (phantom-calib diagnose WORK)"
        )
    if recovery and recovery.get("method") == "spatial":
        lines.append(
            "  reference: the prestressed loaded mesh (curved stress-free elements; no straight "
            "stress-free mesh exists on this model mesh)"
        )
    return lines


def format_calibration(doc: dict) -> str:
    """A readable summary of calibration.json."""
    ci = doc["c1_ci95_pa"]
    interval = (
        f"95 % interval {ci[0]:.1f} - {ci[1]:.1f} Pa"
        if ci is not None
        else no_interval_said(doc.get("uncertainty", {}).get("interval"))
    )
    lines = [
        f"c1 = {doc['c1_pa']:.1f} Pa  ({interval}), objective {doc['objective']}, "
        + reference_state_said(doc["reference_state"], doc.get("reference_recovery")),
        f"{doc['iterations']} iterations, {doc['fe_solves']} FE solves in all, "
        f"{doc['wall_s']:.0f} s",
        *_uncertainty_lines(doc.get("uncertainty", {}), doc["objective"]),
        *_optimiser_lines(doc.get("optimiser")),
        *_model_fit_lines(doc.get("model_fit"), doc.get("reference_recovery")),
        f"{'scan':<16}{'role':<13}{'surface mean+-sd (fiducial)':>29}{'(icp)':>16}"
        f"{'nipple mm':>11}{'tumour mm':>11}",
    ]
    for name, s in doc["scans"].items():
        if s.get("failed"):
            lines.append(f"{name:<16}{s['role']:<13}  no FE solution: {s['failed']}")
            continue
        fid, icp = s["surface_error_mm"]["fiducial"], s["surface_error_mm"]["icp"]
        tum = s.get("tumour_error_mm", {}).get("fiducial")
        lines.append(
            f"{name:<16}{s['role']:<13}{fid['mean']:>20.2f} +- {fid['sd']:.2f}"
            f"{icp['mean']:>11.2f} +- {icp['sd']:.2f}{s['nipple_error_mm']['fiducial']:>9.2f}"
            f"{'' if tum is None else f'{tum:.2f}':>11}"
        )
    return "\n".join(lines)


def _band(b: dict | None, fmt: str = ".2f") -> str:
    if b is None:
        return "–"
    ci = b.get("ci95")
    return f"{b['value']:{fmt}}" + ("" if ci is None else f" ({ci[0]:{fmt}}–{ci[1]:{fmt}})")


def _plane(scan: dict) -> str:
    """``°`` after a transverse posture angle, ``°s`` after a sagittal one."""
    return "°s" if scan.get("posture_plane") == "sagittal" else "° "


def _reference(ref: dict) -> str:
    if ref.get("surface_mean_mm") is not None:
        tumour = "" if ref.get("tumour_mm") is None else f", tumour {ref['tumour_mm']:.2f}"
        return f"{ref['surface_mean_mm']} ± {ref['surface_sd_mm']}{tumour}"
    if ref.get("nipple_mm") is not None:
        return f"nipple {ref['nipple_mm']}"
    return ""


def format_validation(doc: dict) -> str:
    """A readable summary of validation.json: one line per scan (fiducial frame, mm)."""
    lines = [
        f"{'scan':<16}{'role':<13}{'posture':>8}  {'surface mean (95 % band)':<26}"
        f"{'sd':>6}  {'nipple':<22}{'tumour':<22}{'dissertation':<20}"
    ]
    for name, s in doc["scans"].items():
        surf = s["surface_error_mm"]["fiducial"]
        tumour = (s.get("tumour_error_mm") or {}).get("fiducial")
        nipple = s["nipple_error_mm"]["fiducial"]
        lines.append(
            f"{name:<16}{s['role']:<13}{s['posture_angle_deg']:>6.0f}{_plane(s)}  "
            f"{_band(surf['mean']):<26}{surf['sd']['value']:>6.2f}  "
            f"{_band(nipple):<22}{_band(tumour):<22}{_reference(s.get('dissertation') or {}):<20}"
        )
    for name, why in (doc.get("failed") or {}).items():
        lines.append(f"{name:<16}not validated: no FE solution at calibration ({why})")
    if doc["scans"]:
        lines.append(f"posture: {POSTURE_NOTE}")
    lines += [f"WARNING (calibration): {said}" for said in doc.get("calibration_caveats") or []]
    from ..validation import no_validation_scan_note, simulated_scans_note

    roles = (s["role"] for s in doc["scans"].values())
    notes = simulated_scans_note(doc.get("scans_source")) + no_validation_scan_note(roles)
    lines += [f"WARNING: {said}" for said in notes]
    if any(s.get("dissertation") for s in doc["scans"].values()):
        lines.append(
            "dissertation: its published figures for the original CIRS phantom's scans (a "
            "baseline to compare with, not figures of this phantom)"
        )
    return "\n".join(lines)
