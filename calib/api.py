"""Notebook-level functions: one call per pipeline stage.

They wrap :mod:`calib.workflows` (which write WORK/ exactly as the command line does):
``ingest`` returns an :class:`calib.data.ingest.IngestResult`, ``calibrate``,
``validate``, ``diagnose``, ``simulate``, ``gravity_sweep`` and ``train_surrogate`` their
records (dicts),
``load_work`` a :class:`calib.notebook.Work` and ``load_surrogate`` an
:class:`nn.Surrogate`. ``gravity_sweep`` is the ``sweep`` command (``calib.sweep`` is the
subpackage of its plans and store).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # annotations only: ``import calib`` stays light
    import nn
    from nn.device import Device

    from .choices import SurrogateKind
    from .data.ingest import IngestResult
    from .data.work import WorkFolder
    from .discrepancy import DiagnosisOptions
    from .fitting import CalibrationOptions
    from .notebook import Work
    from .workflows.simulate import SimulateOptions
    from .workflows.sweep import SweepOptions

__all__ = [
    "calibrate",
    "diagnose",
    "gravity_sweep",
    "ingest",
    "load_surrogate",
    "load_work",
    "simulate",
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


def _work_path(work: str | Path | Work | WorkFolder) -> str | Path:
    """The path of a work folder given as a path, a ``Work`` or a ``WorkFolder``.

    Review BZ, F6: the loaded objects failed with "expected str, bytes or os.PathLike".
    """
    from .data.work import WorkFolder
    from .notebook import Work

    if isinstance(work, Work):
        return work.folder.path
    if isinstance(work, WorkFolder):
        return work.path
    return work


def ingest(
    scans: str | Path, work: str | Path, *, progress: Callable[[str], Any] | None = None
) -> IngestResult:
    """Ingest the scan folder ``scans`` into ``work`` (``phantom-calib ingest``).

    Parameters
    ----------
    scans : str or Path
        The scan folder, holding ``session.toml``.
    work : str or Path
        The work folder to write (created); per-scan results go to ``work/scans/<name>/``.
    progress : callable, optional
        Called with each scan's name when it has been processed.

    Returns
    -------
    calib.data.ingest.IngestResult
        The session, the per-scan results, the registrations to the reference scan and
        the tumour tracking.

    Raises
    ------
    calib.data.SessionError
        ``scans/session.toml`` is missing or invalid (:func:`calib.load_session`).
    """
    from .workflows.ingest import run_ingest

    return run_ingest(scans, work, progress=progress)


def calibrate(
    scans: str | Path,
    work: str | Path,
    *,
    options: CalibrationOptions | None = None,
    progress: Callable[[str], Any] | None = None,
    **fields: Any,
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
    **fields
        :class:`calib.CalibrationOptions` fields by name, when ``options`` is not given.

    Returns
    -------
    dict
        The ``calibration.json`` record.

    Raises
    ------
    TypeError
        Both ``options`` and ``fields`` are given, ``options`` is not a
        ``CalibrationOptions``, or a field name is unknown.
    """
    from .fitting import CalibrationOptions
    from .workflows.calibrate import run_calibration

    return run_calibration(
        scans, work, _options(CalibrationOptions, options, fields), progress=progress
    )


def validate(work: str | Path | Work, *, progress: Callable[[str], Any] | None = None) -> dict:
    """Write the validation report of a calibrated work folder (``phantom-calib validate``).

    Parameters
    ----------
    work : str, Path or calib.notebook.Work
        A work folder ``calibrate`` wrote; the report goes into it. Given a loaded
        :class:`~calib.notebook.Work`, it keeps the figures computed, so that its
        ``validation_table()`` and plots do not compute them again (review BW, F8).
    progress : callable, optional
        Called with a line of text at every step.

    Returns
    -------
    dict
        The ``validation.json`` record.

    Raises
    ------
    FileNotFoundError
        ``work`` has no ``calibration.json`` or misses a file it names.
    calib.io.StaleOutputError
        ``work``'s calibration does not match its ``calibration/`` or its scans were
        ingested again after it.
    """
    from .notebook import Work
    from .workflows.validate import run_validation

    path, kept = _work_path(work), {}
    if isinstance(work, Work):

        def keep(v, written):
            if not work.keep_validation(v, written.get("calibration_run_id")):
                log.warning(
                    "%s was calibrated again since it was loaded: its report is of the new "
                    "calibration, the loaded object keeps the old one's states (load it again)",
                    path,
                )

        kept["on_validation"] = keep
    record = run_validation(path, progress=progress, **kept)
    for said in record.get("calibration_caveats") or []:  # the command prints them
        log.warning("calibration: %s", said)
    return record


def load_work(work: str | Path) -> Work:
    """A calibrated work folder as an object (:class:`calib.notebook.Work`), for notebooks.

    Parameters
    ----------
    work : str or Path
        A work folder ``calibrate`` wrote.

    Returns
    -------
    calib.notebook.Work
        Its records, states and plots (c1 in Pa, geometry in the ref frame, mm).

    Raises
    ------
    FileNotFoundError
        ``work`` has no ``calibration.json`` or misses a file it names.
    calib.io.StaleOutputError
        ``work``'s calibration does not match its ``calibration/`` or its scans were
        ingested again after it.
    """
    from .notebook import Work

    return Work.load(work)


def diagnose(
    work: str | Path | Work,
    *,
    options: DiagnosisOptions | None = None,
    progress: Callable[[str], Any] | None = None,
    **fields: Any,
) -> dict:
    """Diagnose a calibrated work folder's missing effect (``phantom-calib diagnose``).

    Parameters
    ----------
    work : str, Path or calib.notebook.Work
        A calibrated work folder (or one loaded by :func:`load_work`).
    options : calib.discrepancy.DiagnosisOptions, optional
        The options; or give their fields as keywords (``effects=("skin",)``), not both.
    progress : callable, optional
        Called with a line of text at every step.
    **fields
        :class:`calib.DiagnosisOptions` fields by name, when ``options`` is not given.

    Returns
    -------
    dict
        The ``diagnosis.json`` record; ``WORK/diagnosis/refit`` is a work folder that
        :func:`load_work` and :func:`validate` accept.

    Raises
    ------
    TypeError
        Both ``options`` and ``fields`` are given, ``options`` is not a
        ``DiagnosisOptions``, or a field name is unknown.
    """
    from .discrepancy import DiagnosisOptions
    from .workflows.diagnose import run_diagnosis

    opts = _options(DiagnosisOptions, options, fields)
    return run_diagnosis(_work_path(work), opts, progress=progress)


def simulate(
    mesh: str | Path,
    out: str | Path,
    *,
    options: SimulateOptions | None = None,
    **fields: Any,
) -> dict:
    """Deform a mesh under gravity at a given c1 (``phantom-calib simulate``).

    Parameters
    ----------
    mesh : str or Path
        A tetrahedral mesh, mm (any format meshio reads, or TetGen ``.node``/``.ele``):
        a calibration's ``WORK/calibration/reference_mesh.vtu``, or one of your own.
    out : str or Path
        The deformed mesh to write (its format from the suffix), in the input's point
        numbering, with ``RESULT.json``'s record beside it (``out`` with ``.json``).
    options : calib.SimulateOptions, optional
        The options; or give their fields as keywords (``c1_pa=550.0,
        gravity=(0, 1, 0)``), not both. ``c1_pa`` has no default.
    **fields
        :class:`calib.SimulateOptions` fields by name, when ``options`` is not given.

    Returns
    -------
    dict
        The ``RESULT.json`` record (``max_displacement_mm``, ``nipple_displacement_mm``,
        ``back``, ``converged``, ...; README, "simulate").

    Raises
    ------
    TypeError
        Both ``options`` and ``fields`` are given, ``options`` is not a
        ``SimulateOptions``, or a field name is unknown (or ``c1_pa`` missing).
    ValueError
        An option out of range; ``fem.MeshError`` (a ``ValueError``) for a mesh that
        cannot be solved, naming the file.
    fem.ConvergenceError
        The load could not be applied.
    """
    from .workflows.simulate import SimulateOptions, run_simulate

    return run_simulate(mesh, out, _options(SimulateOptions, options, fields))


def gravity_sweep(
    work: str | Path | Work,
    out: str | Path,
    *,
    options: SweepOptions | None = None,
    progress: Callable[[dict], Any] | None = None,
    **fields: Any,
) -> dict:
    """Solve a calibrated model over a plan of gravity directions (``phantom-calib sweep``).

    Parameters
    ----------
    work : str, Path or calib.notebook.Work
        A calibrated work folder (or one loaded by :func:`load_work`).
    out : str or Path
        The Zarr store to write, or to resume where it holds this model's and plan's sweep.
    options : calib.workflows.sweep.SweepOptions, optional
        The options; or give their fields as keywords (``plan="sphere:24"``), not both.
    progress : callable, optional
        Called with a dict after each solved scenario (see
        :func:`calib.workflows.sweep.run_sweep`); ``calib.sweep.progress_lines(print)``
        turns them into lines of text, as the other stages' callbacks get.
    **fields
        :class:`calib.SweepOptions` fields by name, when ``options`` is not given.

    Returns
    -------
    dict
        The sweep's summary (also in the store's ``summary`` attribute).

    Raises
    ------
    TypeError
        Both ``options`` and ``fields`` are given, ``options`` is not a ``SweepOptions``,
        or a field name is unknown.
    """
    from .workflows.sweep import SweepOptions, run_sweep

    opts = _options(SweepOptions, options, fields)
    return run_sweep(_work_path(work), out, opts, progress=progress)


def train_surrogate(
    sweep: str | Path,
    out: str | Path,
    *,
    kind: SurrogateKind = "ours",
    device: Device = "auto",
    seed: int = 0,
    iterations: int | None = None,
    progress: Callable[[str], Any] | None = None,
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
        Where training runs; ``auto`` takes CUDA when present.
    seed : int
        Seed of the MLPs' initialisation and batches.
    iterations : int, optional
        Training iterations of the dissertation's MLPs (default 30 000).
    progress : callable, optional
        Called with a line of text.

    Returns
    -------
    dict
        The training report (also inside the model file); :func:`load_surrogate` reads
        the model.

    Raises
    ------
    ValueError
        An unknown ``kind`` or ``device``, ``cuda`` without a CUDA device, ``iterations``
        below 1 or given for ``ours``, or ``out`` not ``.pt``.
    IsADirectoryError
        ``out`` is a folder.
    nn.StoreFormatError
        ``sweep`` is not a readable sweep store, or has pending scenarios.
    """
    from .workflows.sweep import run_surrogate_train

    return run_surrogate_train(
        sweep, out, kind=kind, device=device, seed=seed, iterations=iterations, progress=progress
    )


def load_surrogate(path: str | Path) -> nn.Surrogate:
    """A surrogate file as an :class:`nn.Surrogate` (its ``predict(gravity_m_s2, c1_pa=...)``).

    Parameters
    ----------
    path : str or Path
        A model file :func:`train_surrogate` wrote (``.pt``).

    Returns
    -------
    nn.Surrogate

    Raises
    ------
    nn.SurrogateFileError
        Missing file, a folder, not a TorchScript archive, or no phantom-calib metadata.
    """
    import nn

    return nn.load_surrogate(path)
