"""Gravity sweeps of a calibrated model: plans, continuation, engine and store.

``phantom-calib sweep WORK --out SWEEP`` (:func:`calib.workflows.sweep.run_sweep`) solves
the calibrated model under many gravity directions (and c1 values) and writes a Zarr
store (:mod:`calib.sweep.store`, whose docstring documents the format) that
:mod:`nn` reads to train surrogates.
"""

from .continuation import Continuation, plan_continuation
from .model import CalibrationMissingError, SweepModel, load_sweep_model
from .plans import Plan, PlanError, make_plan, parse_c1_axis
from .progress import progress_lines

__all__ = [
    "CalibrationMissingError",
    "Continuation",
    "Plan",
    "PlanError",
    "SweepModel",
    "load_sweep_model",
    "make_plan",
    "parse_c1_axis",
    "plan_continuation",
    "progress_lines",
]
