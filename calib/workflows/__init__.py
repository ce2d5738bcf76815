"""Commands as functions: the only code that writes into a work folder (WORK/)."""

from .calibrate import run_calibration, write_calibration
from .ingest import run_ingest, write_ingest
from .simulate import SimulateOptions, run_simulate

__all__ = [
    "SimulateOptions",
    "run_calibration",
    "run_ingest",
    "run_simulate",
    "write_calibration",
    "write_ingest",
]
