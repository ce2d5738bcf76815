"""Sizes of the example notebooks, chosen by the environment variable PHANTOM_CALIB_SIZE.

``tiny`` (the notebook tests: a coarse three-posture twin, a few minutes on 2 cores),
``quick`` (the default of ``make notebooks``) or ``dissertation``. Outputs go to
PHANTOM_CALIB_OUT (default ``examples/out/<SIZE>``: a run at another size keeps its own
twin, work folder and sweep store), shared by the notebooks in order.
"""

from __future__ import annotations

import os
from pathlib import Path

SIZE = os.environ.get("PHANTOM_CALIB_SIZE", "quick")
if SIZE not in ("tiny", "quick", "dissertation"):
    raise ValueError(f"PHANTOM_CALIB_SIZE must be tiny, quick or dissertation, not {SIZE!r}")
# review AG: one folder for all sizes made notebook 03 refuse the sweep store of another
# size's model; each size now has its own folder
OUT = Path(os.environ.get("PHANTOM_CALIB_OUT", Path(__file__).resolve().parent / "out" / SIZE))


def preset():
    """The twin preset of this size."""
    from calib.twin import PRESETS, Posture, TwinPreset

    if SIZE != "tiny":
        return PRESETS[SIZE]
    return TwinPreset(
        phantom_resolution_mm=14,
        truth_mesh_mm=10,  # the truth finer than the model (14 mm): no inverse crime
        spacing_mm=(2.0, 2.0, 2.0),
        postures=(
            Posture("left_lateral", 0, "reference"),
            Posture("right_lateral", 180, "calibration"),
            Posture("tilt_50", 50, "validation"),
        ),
    )


def calibration_options() -> dict:
    """Options of ``calib.calibrate`` for this size."""
    if SIZE == "tiny":
        return {"mesh_size_mm": 14.0, "mesh_retry_mm": (), "profile_points": 0}
    return {}
