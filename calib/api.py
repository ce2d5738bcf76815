"""Notebook-level functions: one call per pipeline stage.

They wrap :mod:`calib.workflows` (which write WORK/ exactly as the command line does):
``ingest`` returns an :class:`calib.data.ingest.IngestResult`, ``calibrate``,
``validate``, ``diagnose``, ``gravity_sweep`` and ``train_surrogate`` their records (dicts),
``load_work`` a :class:`calib.notebook.Work` and ``load_surrogate`` an
:class:`nn.Surrogate`. ``gravity_sweep`` is the ``sweep`` command (``calib.sweep`` is the
subpackage of its plans and store).
"""

from __future__ import annotations

import logging
from pathlib import Path

__all__ = [
    "calibrate",
    "diagnose",
    "gravity_sweep",
    "ingest",
    "load_surrogate",
    "load_work",
    "train_surrogate",
    "validate",
]

log = logging.getLogger(__name__)


def _options(cls, options, fields: dict):
    """``options`` (a ``cls``), or a ``cls`` made of ``fields``; not both."""
    if options is not None and fields:
        raise TypeError(f"give options or its fields as keywords, not both ({sorted(fields)})")
    if options is not None and not isinstance(options, cls):
        raise TypeError(f"options must be a {cls.__name__}, got {type(options).__name__}")
    return options if options is not None else cls(**fields)


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

    return run_calibration(
        scans, work, _options(CalibrationOptions, options, fields), progress=progress
    )


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


def diagnose(work, *, options=None, progress=None, **fields) -> dict:
    """Diagnose a calibrated work folder's missing effect (``phantom-calib diagnose``).

    Parameters
    ----------
    work : str or Path
        A calibrated work folder.
    options : calib.discrepancy.DiagnosisOptions, optional
        The options; or give their fields as keywords (``effects=("skin",)``), not both.
    progress : callable, optional
        Called with a line of text at every step.

    Returns
    -------
    dict
        The ``diagnosis.json`` record; ``WORK/diagnosis/refit`` is a work folder that
        :func:`load_work` and :func:`validate` accept.
    """
    from .discrepancy import DiagnosisOptions
    from .workflows.diagnose import run_diagnosis

    return run_diagnosis(work, _options(DiagnosisOptions, options, fields), progress=progress)


def gravity_sweep(work, out, *, options=None, progress=None, **fields) -> dict:
    """Solve a calibrated model over a plan of gravity directions (``phantom-calib sweep``).

    Parameters
    ----------
    work : str or Path
        A calibrated work folder.
    out : str or Path
        The Zarr store to write, or to resume where it holds this model's and plan's sweep.
    options : calib.workflows.sweep.SweepOptions, optional
        The options; or give their fields as keywords (``plan="sphere:24"``), not both.
    progress : callable, optional
        Called with a dict after each solved scenario (see
        :func:`calib.workflows.sweep.run_sweep`).

    Returns
    -------
    dict
        The sweep's summary (also in the store's ``summary`` attribute).
    """
    from .workflows.sweep import SweepOptions, run_sweep

    return run_sweep(work, out, _options(SweepOptions, options, fields), progress=progress)


def train_surrogate(
    sweep, out, *, kind="ours", device="auto", seed=0, iterations=None, progress=None
) -> dict:
    """Train a surrogate on a sweep store and write it (``phantom-calib surrogate train``).

    Parameters
    ----------
    sweep : str or Path
        A store :func:`gravity_sweep` wrote.
    out : str or Path
        The model file to write (``.pt``, TorchScript).
    kind : {"ours", "dissertation"}
        The reduced-basis kernel surrogate, or the dissertation's two MLPs.
    device : {"auto", "cpu", "cuda"}
    seed : int
        Seed of the MLPs' initialisation and batches.
    iterations : int, optional
        Training iterations of the dissertation's MLPs (default 30 000).
    progress : callable, optional

    Returns
    -------
    dict
        The training report (also inside the model file); :func:`load_surrogate` reads
        the model.
    """
    from .workflows.sweep import run_surrogate_train

    return run_surrogate_train(
        sweep, out, kind=kind, device=device, seed=seed, iterations=iterations, progress=progress
    )


def load_surrogate(path):
    """A surrogate file as an :class:`nn.Surrogate` (its ``predict(gravity_m_s2, c1_pa=...)``)."""
    import nn

    return nn.load_surrogate(path)
