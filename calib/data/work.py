"""A calibrated work folder read back: the record, the measurements and the saved states.

Everything :mod:`calib.workflows.calibrate` wrote into ``WORK/`` — the
``calibration.json`` record, the stress-free model mesh and every scan's deformed
state (vertex positions and their derivative in ln c1) — with the measurements of
``WORK/scans/``, so results can be re-measured, validated and plotted without FE.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from types import MappingProxyType

import numpy as np

from ..io import StaleOutputError, check_run, file_sha256, run_id_of
from .measurements import Measurements, read_scan
from .session import ScanEntry, is_finite_number

__all__ = [
    "SCHEMA_VERSION",
    "ReadOnlyDict",
    "ReadOnlyList",
    "SavedState",
    "WorkFolder",
    "as_work_folder",
    "check_record",
    "not_a_folder",
    "read_only_record",
    "read_work",
]

#: Version of ``calibration.json``. 1: the keys of phantom-calib 0.1 plus
#: ``schema_version``, ``optimiser`` and ``model``. A record without it is 0.1's; one of a
#: later version is refused by :func:`check_record` (its keys may mean other things).
SCHEMA_VERSION = 1


@dataclass(frozen=True, eq=False)
class SavedState:
    """A scan's simulated state at the calibrated c1, as saved by ``calibrate``.

    Its arrays are read-only, and two states are equal only if they are the same object
    (review AI: ``==`` raised on the arrays).

    Attributes
    ----------
    positions_mm : ndarray, shape (n_nodes, 3)
        Deformed vertex positions of the model mesh, reference frame.
    dpositions_mm : ndarray, shape (n_nodes, 3) or None
        Their derivative in ln c1 (mm per unit ln c1).
    reference_positions_mm : ndarray, shape (n_nodes, 3) or None
        The same vertices in the loaded reference scan (for displacement magnitudes).
    tumour_mm, dtumour_mm : ndarray, shape (3,) or None
        Simulated tumour centre and its derivative in ln c1.
    """

    positions_mm: np.ndarray
    dpositions_mm: np.ndarray | None
    reference_positions_mm: np.ndarray | None
    tumour_mm: np.ndarray | None
    dtumour_mm: np.ndarray | None

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, _read_only(getattr(self, f.name)))


def _read_only(value) -> np.ndarray | None:
    """``value`` as a read-only float array (None stays None)."""
    if value is None:
        return None
    array = np.array(value, float)
    array.setflags(write=False)
    return array


def _refuse(self, *args, **kwargs):
    raise TypeError(
        "a work folder's calibration.json record is read-only (review BW, F3: changing it "
        "changed what the folder reports); copy.deepcopy(...) gives a plain copy to edit"
    )


class _ReadOnly:
    """Copies of a read-only JSON container: plain and editable; pickles read-only."""

    __slots__ = ()
    _plain: type

    def __copy__(self):
        return self._plain(self)

    def __deepcopy__(self, memo):
        return _thawed(self)

    def __reduce__(self):
        return (read_only_record, (_thawed(self),))


class ReadOnlyDict(_ReadOnly, dict):
    """A JSON record's mapping that refuses changes (a ``dict`` to readers and ``json``).

    ``copy.deepcopy`` gives a plain, editable copy at every depth; ``copy.copy`` (like
    ``dict(record)``) a plain top level whose nested values stay read-only.
    """

    __slots__ = ()
    _plain = dict
    __setitem__ = __delitem__ = __ior__ = _refuse
    clear = pop = popitem = setdefault = update = _refuse


class ReadOnlyList(_ReadOnly, list):
    """A JSON record's list that refuses changes (a ``list`` to readers and ``json``)."""

    __slots__ = ()
    _plain = list
    __setitem__ = __delitem__ = __iadd__ = __imul__ = _refuse
    append = clear = extend = insert = pop = remove = reverse = sort = _refuse


def _thawed(value):
    """A plain, editable deep copy of a JSON value."""
    if isinstance(value, dict):
        return {k: _thawed(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_thawed(v) for v in value]
    return value


def read_only_record(value):
    """``value`` (a JSON value) with every mapping and list read-only, at every depth.

    Parameters
    ----------
    value : dict, list, str, float, int, bool or None
        A value as :func:`json.load` returns it.

    Returns
    -------
    ReadOnlyDict, ReadOnlyList or the value itself
        Equal to ``value``; its mappings and lists raise ``TypeError`` when changed.
    """
    if isinstance(value, dict):
        return ReadOnlyDict((k, read_only_record(v)) for k, v in value.items())
    if isinstance(value, list):
        return ReadOnlyList(read_only_record(v) for v in value)
    return value


@dataclass(frozen=True, eq=False)
class WorkFolder:
    """A calibrated ``WORK/`` folder (see :func:`read_work`; equal only to itself).

    Attributes
    ----------
    path : Path
    record : ReadOnlyDict
        ``calibration.json``, read-only at every depth (``copy.deepcopy`` gives an
        editable copy).
    measurements : Measurements
        Every scan of the calibration, with the roles it was calibrated with.
    mesh : fem.TetMesh
        The stress-free model mesh (node sets ``back``, ``nipple``, ``surface``).
    states : mapping of str to SavedState
        Scans with a solution at the calibrated c1 (a read-only mapping).
    """

    path: Path
    record: dict
    measurements: Measurements
    mesh: object
    states: Mapping[str, SavedState]

    def __post_init__(self) -> None:  # review BW, F3: the folder changed through these
        object.__setattr__(self, "record", read_only_record(self.record))
        object.__setattr__(self, "states", MappingProxyType(dict(self.states)))

    def __reduce__(self):  # a mapping proxy does not pickle: rebuilt from plain copies
        record, states = _thawed(self.record), dict(self.states)
        return (WorkFolder, (self.path, record, self.measurements, self.mesh, states))

    def __repr__(self) -> str:  # review BW, F4: 25,000 characters of record and arrays
        return (
            f"WorkFolder({str(self.path)!r}: c1 = {self.c1_pa:.1f} Pa, "
            f"{len(self.measurements.scans)} scans, {len(self.states)} solved states)"
        )

    @property
    def c1_pa(self) -> float:
        """The calibrated c1 (Pa)."""
        return float(self.record["c1_pa"])

    @property
    def ln_c1_interval(self) -> tuple[float, float] | None:
        """The 95 % interval of ln c1, or None."""
        ci = self.record.get("c1_ci95_pa")
        return None if ci is None else (float(np.log(ci[0])), float(np.log(ci[1])))

    @property
    def nipple_node(self) -> int:
        """The model's nipple vertex."""
        return int(self.mesh.node_set("nipple")[0])


def _entry(name: str, role: str, posture: dict | None, work: Path) -> ScanEntry:
    """A scan as calibration.json records it (no ``posture`` in older files: none given)."""
    posture = posture or {}
    return ScanEntry(name, work, role, posture.get("plane"), posture.get("angle_deg"))


def _check_ingest_hashes(work: Path, record: dict) -> None:
    """A record without ``ingest_run_id`` (before 2026-12-06): its scans' ingest hashes.

    Such records name each scan's ``ingest.json`` with its SHA-256 in their provenance;
    a scan ingested again since (another scan set, or an interrupted calibrate's new
    ingest) was read with the old fit (review AN: errors of 16-19 mm, exit status 0).
    """
    inputs = (record.get("provenance") or {}).get("inputs") or {}
    for key, entry in inputs.items():
        if not (key.endswith("/ingest.json") and isinstance(entry, dict) and entry.get("sha256")):
            continue
        path = work / "scans" / key
        if not path.is_file() or file_sha256(path) != entry["sha256"]:
            raise StaleOutputError(
                f"{path}: {'missing' if not path.is_file() else 'not the file'} this "
                "calibration fitted (calibration.json's provenance holds its SHA-256): the "
                "scans were ingested again after it; run `phantom-calib calibrate` again"
            )


def not_a_folder(work: Path, *, missing: str = "no such work folder") -> str | None:
    """Why ``work`` is no work folder to read, or None where it is a folder.

    Review AI, AT: a mistyped folder, or the record's own path (``WORK/calibration.json``),
    which was called missing although it exists.
    """
    if work.is_dir():
        return None
    return "is a file: pass the work folder that holds it" if work.exists() else missing


def read_work(work: str | Path, *, unreadable_states: list | None = None) -> WorkFolder:
    """Read a calibrated work folder.

    Parameters
    ----------
    work : str or Path
        A work folder ``phantom-calib calibrate`` wrote.
    unreadable_states : list, optional
        Where given, a scan's saved FE state that is missing or cannot be read is left
        out of ``states`` and its error message appended here, instead of raised (the
        browser view shows the other scans: review CD-6); the folder's other files are
        read as without it.

    Returns
    -------
    WorkFolder

    Raises
    ------
    FileNotFoundError
        No ``calibration.json`` (run ``phantom-calib calibrate`` first) or a missing file
        it names.
    calib.io.StaleOutputError
        ``calibration/`` is not from the run ``calibration.json`` records, or ``scans/``
        was ingested again after the calibration (its ``ingest_run_id``; in an older
        record without it, the ``ingest.json`` hashes of its provenance).
    """
    from fem.io import read_mesh

    work = Path(work)
    if why := not_a_folder(work, missing="no such folder"):
        raise FileNotFoundError(f"{work}: {why}")
    try:
        record = check_run(work, folder="calibration", record="calibration.json")
    except FileNotFoundError as exc:
        raise FileNotFoundError(
            f"{work}: no calibration.json (run `phantom-calib calibrate` first)"
        ) from exc
    check_record(record, work / "calibration.json")
    fitted = record.get("ingest_run_id")
    if fitted is not None and (held := run_id_of(work / "scans")) != fitted:
        # review AI: a new ingest into a calibrated WORK was read with the old fit's
        # states, and validate reported errors 4-8 times the fitted scans'
        raise StaleOutputError(
            f"{work / 'scans'} was ingested again after this calibration (it fitted ingest "
            f"run {fitted}, the folder holds run {held}): its scans are not those "
            "calibrated; run `phantom-calib calibrate` again"
        )
    if fitted is None:
        _check_ingest_hashes(work, record)
    model = record.get("model") or {}
    ref_name = model.get("reference_scan")
    if ref_name is None or "reference_mesh" not in model:
        raise ValueError(
            f"{work / 'calibration.json'}: written by an older phantom-calib "
            "(no `model` block); run `phantom-calib calibrate` again"
        )
    if not record.get("scans"):  # review AT: a bare KeyError 'scans'; {} validated nothing
        raise ValueError(f"{work / 'calibration.json'}: no `scans` (the calibrated scans)")
    entries = [_entry(ref_name, "reference", model.get("reference_posture"), work)] + [
        _entry(name, s["role"], s.get("posture"), work) for name, s in record["scans"].items()
    ]
    scans = {e.name: read_scan(work, e) for e in entries}
    measurements = Measurements(scans[ref_name], scans, model.get("density_kg_m3"))
    mesh = read_mesh(work / model["reference_mesh"], orient=False)
    states = {}
    for name, s in record["scans"].items():
        if s.get("failed"):
            continue
        deformed = work / "calibration" / f"{name}_deformed.vtu"
        try:
            data = _point_data(deformed)
            if data.get("displacement_mm", np.empty(0)).shape != mesh.nodes_mm.shape:
                raise ValueError(
                    f"{deformed}: no `displacement_mm` point data of the reference mesh's "
                    f"{mesh.n_nodes} nodes (calibrate writes it)"
                )
        except (OSError, ValueError) as exc:
            if unreadable_states is None:
                raise
            unreadable_states.append(str(exc))
            continue
        positions = mesh.nodes_mm + data["displacement_mm"]
        ref = data.get("displacement_from_reference_mm")
        states[name] = SavedState(
            positions_mm=positions,
            dpositions_mm=data.get("dposition_dlnc1_mm"),
            reference_positions_mm=None if ref is None else positions - ref,
            tumour_mm=s.get("model", {}).get("tumour_mm"),
            dtumour_mm=s.get("model", {}).get("dtumour_dlnc1_mm"),
        )
    return WorkFolder(work, record, measurements, mesh, states)


def as_work_folder(work) -> WorkFolder:
    """A calibrated work folder from what a caller holds.

    Parameters
    ----------
    work : WorkFolder, str, Path or calib.notebook.Work
        A path is read (:func:`read_work`); ``calib.load_work``'s object gives its folder.

    Raises
    ------
    TypeError
        Anything else.
    """
    if isinstance(work, WorkFolder):
        return work
    if isinstance(work, str | Path):
        return read_work(work)
    if isinstance(getattr(work, "folder", None), WorkFolder):  # calib.load_work's Work
        return work.folder
    raise TypeError(
        "expected a work folder: its path, calib.load_work(...) or calib.data.read_work(...), "
        f"got {type(work).__name__}"
    )


def check_record(record: dict, path: Path) -> None:
    """Refuse a ``calibration.json`` whose keys the readers use have the wrong shape.

    A hand-edited or foreign file gave tracebacks (``scans`` a list, ``c1_pa`` null, a
    one-element interval): now a ``ValueError`` naming the key and what was expected.
    ``read_work`` and the sweep's model reader both check through it.

    Parameters
    ----------
    record : dict
        The parsed ``calibration.json``.
    path : Path
        Its file, named in the message.

    Raises
    ------
    ValueError
        ``schema_version`` later than :data:`SCHEMA_VERSION` or not an integer;
        ``c1_pa`` not a positive finite number; ``c1_ci95_pa`` neither null nor a finite
        ``[low, high]`` with ``0 < low <= high`` that holds ``c1_pa`` (1 % slack);
        ``model`` not an object, or its keys the readers use of the wrong type or range
        (strings, numbers, the rotation, the prestress files, ``effects``); ``scans``
        not an object of records with the role ``calibration`` or ``validation`` (at
        least one ``calibration``), a posture or model of the wrong shape, or holding
        ``model.reference_scan``; ``scans_source`` neither null nor the session's
        ``[source]``.
    """
    from .session import ROLES

    def bad(key: str, expected: str, got) -> ValueError:
        return ValueError(f"{path}: `{key}` must be {expected}, got {got!r}")

    version = record.get("schema_version", 0)
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise bad("schema_version", f"an integer 0..{SCHEMA_VERSION}", version)
    if version > SCHEMA_VERSION:
        raise ValueError(
            f"{path}: schema_version {version}, written by a newer phantom-calib; this one "
            f"reads {SCHEMA_VERSION} and earlier: update phantom-calib or recalibrate"
        )
    source = record.get("scans_source")  # review BZ, F3: a traceback after validating
    if source is not None and not (
        isinstance(source, dict)
        and set(source) <= {"simulated", "generator"}
        and isinstance(source.get("simulated", False), bool)
        and isinstance(source.get("generator", ""), str)
    ):
        raise bad(
            "scans_source",
            "null or the session's [source]: {simulated: true/false, generator: text}",
            source,
        )
    c1 = record.get("c1_pa")
    if isinstance(c1, bool) or not isinstance(c1, (int, float)) or not (np.isfinite(c1) and c1 > 0):
        raise bad("c1_pa", "a positive number (Pa)", c1)
    ci = record.get("c1_ci95_pa")
    pair = isinstance(ci, list) and len(ci) == 2
    if ci is not None and not (pair and all(isinstance(v, (int, float)) for v in ci)):
        raise bad("c1_ci95_pa", "null or [low, high] in Pa", ci)
    if ci is not None and not (np.all(np.isfinite(ci)) and 0 < ci[0] <= ci[1]):
        raise bad("c1_ci95_pa", "finite, 0 < low <= high (Pa)", ci)
    # c1 inside its own interval (review AT: [100, 200] around 554 Pa gave bands that
    # did not hold the figures); 1 % slack for a profile interval's grid
    if ci is not None and not 0.99 * ci[0] <= c1 <= 1.01 * ci[1]:
        raise bad("c1_ci95_pa", f"an interval that holds c1_pa ({c1:g} Pa)", ci)
    model = record.get("model", {})
    if not isinstance(model, (dict, type(None))):
        raise bad("model", "an object", model)
    _check_model_block(model or {}, bad)
    scans = record.get("scans", {})  # absent: said by the readers that need it
    if not isinstance(scans, dict):
        raise bad("scans", "an object of scan name to its record", scans)
    targets = tuple(r for r in ROLES if r != "reference")  # the reference is model's
    for name, s in scans.items():
        if not isinstance(s, dict) or s.get("role") not in targets:
            raise bad(f"scans.{name}", f"an object with a role among {targets}", s)
        if not isinstance(s.get("posture"), (dict, type(None))):
            raise bad(f"scans.{name}.posture", "null or {plane, angle_deg}", s.get("posture"))
        if not isinstance(s.get("model", {}), dict):
            raise bad(f"scans.{name}.model", "an object", s.get("model"))
        for key in ("tumour_mm", "dtumour_dlnc1_mm"):
            value = s.get("model", {}).get(key)
            if value is not None and not _finite_vector(value, 3):
                raise bad(f"scans.{name}.model.{key}", "null or [x, y, z] (mm)", value)
    ref = (model or {}).get("reference_scan")
    if ref is not None and ref in scans:
        raise bad("model.reference_scan", "the reference scan, not one of `scans`", ref)
    if scans and not any(s["role"] == "calibration" for s in scans.values()):
        raise bad("scans", "records with at least one scan of role 'calibration'", sorted(scans))


def _finite_vector(value, n: int) -> bool:
    """``value`` is a list of ``n`` finite numbers (no booleans)."""
    return isinstance(value, list) and len(value) == n and all(is_finite_number(v) for v in value)


def _check_model_block(model: dict, bad) -> None:
    """The ``model`` keys the readers use, where present (review AT: tracebacks)."""
    for key in ("reference_mesh", "reference_scan", "law"):
        if key in model and not isinstance(model[key], str):
            raise bad(f"model.{key}", "a string", model[key])
    if not isinstance(model.get("reference_posture"), (dict, type(None))):
        raise bad(
            "model.reference_posture", "null or {plane, angle_deg}", model["reference_posture"]
        )
    for key, ok, expected in (
        ("nu", lambda v: 0 < v < 0.5, "a number in (0, 0.5)"),
        ("density_kg_m3", lambda v: v > 0, "a positive number (kg/m^3)"),
        ("g_m_s2", lambda v: v > 0, "a positive number (m/s^2)"),
    ):
        v = model.get(key)
        if key in model and not (is_finite_number(v) and ok(v)):
            raise bad(f"model.{key}", expected, v)
    R = model.get("R_ref_from_phantom")
    if R is not None:
        rows = isinstance(R, list) and len(R) == 3 and all(_finite_vector(r, 3) for r in R)
        M = np.asarray(R, float) if rows else None
        if M is None or not (np.allclose(M.T @ M, np.eye(3), atol=1e-6) and np.linalg.det(M) > 0):
            raise bad("model.R_ref_from_phantom", "a 3x3 rotation (orthonormal, det +1)", R)
    pre = model.get("prestress")
    if pre is not None and not (
        isinstance(pre, dict) and all(isinstance(pre.get(k), str) for k in ("mesh", "state"))
    ):
        raise bad("model.prestress", "null or an object naming its `mesh` and `state` files", pre)
    if "effects" in model and not isinstance(model["effects"], (dict, type(None))):
        raise bad("model.effects", "null or an object", model["effects"])


def read_meshio(path: Path, what: str = "mesh"):
    """``meshio.read(path)``, a failure a ``ValueError`` naming the file.

    Review CD-2: a truncated ``.vtu`` ended the command with meshio's own "Couldn't read
    file" and exit 1 (:func:`fem.io.read_meshio` catches what meshio raises or exits with).
    """
    from fem.io import read_meshio as read

    return read(path, error=lambda why: ValueError(f"{path}: not a readable {what} ({why})"))


def _point_data(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found (named by calibration.json)")
    m = read_meshio(path)
    return {k: np.asarray(v, float) for k, v in m.point_data.items() if not k.startswith("set:")}


def ingest_record(work: WorkFolder, name: str) -> dict:
    """``WORK/scans/<name>/ingest.json`` (:func:`calib.data.ingest.load_ingest`)."""
    from .ingest import load_ingest  # it imports registration: not on every CLI start

    return load_ingest(work.path, name)
