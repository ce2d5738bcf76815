"""Notebook-level functions: one call per pipeline stage.

They wrap :mod:`calib.workflows` (which write WORK/ exactly as the command line does):
``ingest`` returns an :class:`calib.data.ingest.IngestResult`, ``calibrate`` and
``validate`` their records (dicts), ``load_work`` a :class:`calib.notebook.Work`.
"""

from __future__ import annotations

import logging
from pathlib import Path

__all__ = ["calibrate", "ingest", "load_work", "validate"]

log = logging.getLogger(__name__)


def ingest(scans: str | Path, work: str | Path, *, progress=None):
    """Ingest the scan folder ``scans`` into ``work`` (``phantom-calib ingest``).

    Returns
    -------
    calib.data.ingest.IngestResult
    """
    from .workflows.ingest import run_ingest

    return run_ingest(scans, work, progress=progress)


def calibrate(
    scans: str | Path, work: str | Path, *, options=None, progress=None, **fields
) -> dict:
    """Calibrate c1 (``phantom-calib calibrate``).

    Parameters
    ----------
    scans, work : str or Path
        The scan folder (``session.toml``) and the work folder to write.
    options : CalibrationOptions, optional
        The options, as :func:`calib.fit` takes them; or give their fields as keywords
        (``mesh_size_mm=14``), not both.
    progress : callable, optional
        Called with a line of text at every step.

    Returns
    -------
    dict
        The ``calibration.json`` record.
    """
    from .fitting import CalibrationOptions
    from .workflows.calibrate import run_calibration

    if options is not None and fields:
        raise TypeError(f"give options or its fields as keywords, not both ({sorted(fields)})")
    if options is not None and not isinstance(options, CalibrationOptions):
        raise TypeError(f"options must be a CalibrationOptions, got {type(options).__name__}")
    opts = options if options is not None else CalibrationOptions(**fields)
    return run_calibration(scans, work, opts, progress=progress)


def validate(work: str | Path, *, progress=None) -> dict:
    """Write the validation report of a calibrated work folder (``phantom-calib validate``).

    Returns
    -------
    dict
        The ``validation.json`` record.
    """
    from .workflows.validate import run_validation

    record = run_validation(work, progress=progress)
    for said in record.get("calibration_caveats") or []:  # the command prints them
        log.warning("calibration: %s", said)
    return record


def load_work(work: str | Path):
    """A calibrated work folder as an object (:class:`calib.notebook.Work`), for notebooks."""
    from .notebook import Work

    return Work.load(work)
