"""Calibration benchmark: wall time and FE solves of a full calibration on the twin.

Issue 6 asks for a full calibration of the ``quick`` preset in 2 min or less and of the
``dissertation`` preset in 10 min or less on the 2-core machine, with the number of FE
solves. For each preset this script synthesises the twin (seed 0, the preset's default
hidden effects; or reuses ``--twins DIR/<preset>`` when present), ingests it (timed
apart: imaging, not FE) and runs ``calibrate`` with the default options unless told
otherwise, then prints a table: c1 and its 95 % interval, iterations, FE solves, the
calibration's wall time and the fiducial-frame surface error per scan.

    python benchmarks/bench_calib.py [--presets quick,dissertation] [--twins DIR]
                                     [--objective surface] [--mesh-size 12] [--mesh-check 1.4]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from calib.fitting import CalibrationOptions
from calib.twin import synthesize
from calib.workflows.calibrate import run_calibration
from calib.workflows.ingest import run_ingest


def _twin(root: Path, preset: str) -> tuple[Path, float]:
    out = root / preset
    if (out / "scans" / "session.toml").is_file():
        return out / "scans", 0.0
    t0 = time.perf_counter()
    synthesize(out, preset=preset, seed=0)
    return out / "scans", time.perf_counter() - t0


def run(preset: str, root: Path, options: CalibrationOptions) -> dict:
    scans, t_synth = _twin(root, preset)
    work = root / f"{preset}-work-{options.objective}-{options.reference_state}"
    t0 = time.perf_counter()
    run_ingest(scans, work)
    t_ingest = time.perf_counter() - t0
    doc = run_calibration(scans, work, options)
    return {"synth_s": t_synth, "ingest_s": t_ingest, **doc}


def _print(preset: str, r: dict) -> None:
    ci = r["c1_ci95_pa"]
    ci_txt = f"{ci[0]:.1f}-{ci[1]:.1f}" if ci else "none"
    print(f"{preset}: mesh {r['mesh']['n_tets']} tets, synth {r['synth_s']:.0f} s, "
          f"ingest {r['ingest_s']:.0f} s")  # fmt: skip
    print(f"  c1 {r['c1_pa']:.1f} Pa (95 % {ci_txt}), {r['iterations']} iterations, "
          f"{r['fe_solves']} FE solves, calibration {r['wall_s']:.0f} s")  # fmt: skip
    for name, s in r["scans"].items():
        err = s["surface_error_mm"]["fiducial"]
        print(f"  {name:14s} surface {err['mean']:.2f} +- {err['sd']:.2f} mm (fiducial frame)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="quick", help="comma-separated preset names")
    ap.add_argument("--twins", type=Path, default=None, help="folder of (or for) the twins")
    ap.add_argument("--objective", default="surface")
    ap.add_argument("--reference-state", default="unload")
    ap.add_argument("--mesh-size", type=float, default=CalibrationOptions.mesh_size_mm)
    ap.add_argument("--mesh-check", type=float, default=CalibrationOptions.mesh_check_ratio)
    args = ap.parse_args()
    options = CalibrationOptions(
        objective=args.objective,
        reference_state=args.reference_state,
        mesh_size_mm=args.mesh_size,
        mesh_check_ratio=args.mesh_check,
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = args.twins or Path(tmp)
        for preset in args.presets.split(","):
            _print(preset, run(preset, root, options))


if __name__ == "__main__":
    main()
