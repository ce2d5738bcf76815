"""Notebook-level functions: one call per pipeline stage, results as objects.

They wrap :mod:`calib.workflows` (which write WORK/ exactly as the command line does)
and return Python objects with readable ``repr``s.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["calibrate", "ingest", "load_work", "validate"]


def ingest(scans: str | Path, work: str | Path, *, progress=None):
    """Ingest the scan folder ``scans`` into ``work`` (``phantom-calib ingest``).

    Returns
    -------
    calib.data.ingest.IngestResult
    """
    from .workflows.ingest import run_ingest

    return run_ingest(scans, work, progress=progress)


def calibrate(scans: str | Path, work: str | Path, *, progress=None, **options) -> dict:
    """Calibrate c1 (``phantom-calib calibrate``); keyword options as ``CalibrationOptions``.

    Returns
    -------
    dict
        The ``calibration.json`` record.
    """
    from .fitting import CalibrationOptions
    from .workflows.calibrate import run_calibration

    return run_calibration(scans, work, CalibrationOptions(**options), progress=progress)


def validate(work: str | Path, *, progress=None) -> dict:
    """Write the validation report of a calibrated work folder (``phantom-calib validate``).

    Returns
    -------
    dict
        The ``validation.json`` record.
    """
    from .workflows.validate import run_validation

    return run_validation(work, progress=progress)


def load_work(work: str | Path):
    """A calibrated work folder as an object (:class:`calib.notebook.Work`), for notebooks."""
    from .notebook import Work

    return Work.load(work)
