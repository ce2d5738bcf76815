"""Text tables of calibration results (what the CLI prints)."""

from __future__ import annotations

__all__ = ["format_calibration"]


def _uncertainty_lines(unc: dict) -> list[str]:
    check = unc.get("mesh_check")
    if not check:
        return []
    if unc.get("c1_ci95_pa") is None:
        return []
    lo, hi = unc["c1_ci95_pa"]
    size, c1 = check["check_mesh_size_mm"], check["c1_check_pa"]
    found = f"calibrates to {c1:.1f} Pa" if c1 is not None else f"failed: {check['failure']}"
    return [f"  noise alone: {lo:.1f} - {hi:.1f} Pa; mesh check: the {size:.1f} mm mesh {found}"]


def _optimiser_lines(opt: dict | None) -> list[str]:
    if not opt:
        return []
    lines = []
    if not opt["success"]:
        lines.append(f"  WARNING: the optimiser did not converge: {opt['message']}")
    if opt.get("bound"):
        lines.append(f"  WARNING: c1 ended on the {opt['bound']} bound of its search range "
                     "(x/÷ 4 around the first estimate)")  # fmt: skip
    if opt.get("failed_evaluations"):
        lines.append(f"  {opt['failed_evaluations']} of {opt['evaluations']} evaluations had "
                     "no FE solution")  # fmt: skip
    return lines


def format_calibration(doc: dict) -> str:
    """A readable summary of calibration.json."""
    ci = doc["c1_ci95_pa"]
    interval = (f"95 % interval {ci[0]:.1f} - {ci[1]:.1f} Pa" if ci is not None else
                "no 95 % interval: the data do not bound c1")  # fmt: skip
    lines = [
        f"c1 = {doc['c1_pa']:.1f} Pa  ({interval}), objective "
        f"{doc['objective']}, reference state {doc['reference_state']}",
        f"{doc['iterations']} iterations, {doc['fe_solves']} FE solves, {doc['wall_s']:.0f} s",
        *_uncertainty_lines(doc.get("uncertainty", {})),
        *_optimiser_lines(doc.get("optimiser")),
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
