"""The scan folder: ``session.toml`` and one series (folder) or volume file per scan."""

from __future__ import annotations

import logging
import math
import numbers
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from fem.units import DEFAULT_DENSITY_KG_M3
from registration.rigid import MAX_AUTO_MARKERS

__all__ = [
    "DENSITY_RANGE_KG_M3",
    "ScanEntry",
    "Session",
    "SessionError",
    "checked_density_kg_m3",
    "load_session",
    "scaffold_session",
    "session_inputs",
]

log = logging.getLogger(__name__)

ROLES = ("reference", "calibration", "validation")
PLANES = ("transverse", "sagittal")  # fem.postures.PLANES
#: A scan name is a folder name under WORK/scans/ and part of output file names.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
#: The volume files a scan's path may name (imaging.dicom.VOLUME_FILE_SUFFIXES: imaging is
#: not imported here, so that reading a session stays light; a test keeps the two equal).
VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")
#: scan names taken under ``WORK/scans/`` (compared case-insensitively): the run marker
RESERVED_NAMES = frozenset({"run"})


class SessionError(ValueError):
    """A scan folder or its session.toml is not valid (the message says where and why)."""


@dataclass(frozen=True)
class ScanEntry:
    """One scan of the session.

    Attributes
    ----------
    name : str
    path : Path
        Absolute path to the DICOM series folder or the volume file.
    role : {"reference", "calibration", "validation"}
    posture_plane : str or None
    posture_angle_deg : float or None
        Nominal posture angle, checked against registration.
    """

    name: str
    path: Path
    role: str
    posture_plane: str | None = None
    posture_angle_deg: float | None = None


@dataclass(frozen=True)
class Session:
    """A validated scan session.

    Attributes
    ----------
    folder : Path
    gravity_scanner : ndarray, shape (3,)
        Unit gravity vector in the scanner's LPS frame.
    density_kg_m3 : float
    expected_fiducials : int
    tumour_hint_lps_mm : ndarray or None
        Landmark override: the tracked tumour near this point of the reference scan.
    scans : tuple of ScanEntry
    source : dict
        ``[source]``: ``simulated`` (bool) and ``generator`` (str) where given; empty
        where the file does not say where its scans come from.
    """

    folder: Path
    gravity_scanner: np.ndarray
    density_kg_m3: float
    expected_fiducials: int
    tumour_hint_lps_mm: np.ndarray | None
    scans: tuple[ScanEntry, ...] = field(default_factory=tuple)
    source: dict = field(default_factory=dict)

    @property
    def reference(self) -> ScanEntry:
        """The reference scan (its LPS frame is the ref frame, the model's)."""
        return next(s for s in self.scans if s.role == "reference")

    def by_role(self, role: str) -> list[ScanEntry]:
        """Scans with the given role.

        Parameters
        ----------
        role : {"reference", "calibration", "validation"}

        Returns
        -------
        list of ScanEntry
            In the session's order.
        """
        return [s for s in self.scans if s.role == role]

    def ingest_fingerprint(self, *, paths: Literal["relative", "absolute"] = "relative") -> str:
        """SHA-256 of everything in ``session.toml`` that ingest's results depend on.

        The scanner gravity, the marker count, the tumour hint, which scan is the
        reference, and every scan's name, path and nominal posture. The calibration and
        validation roles are not part of it: they are read from the session every time.

        Parameters
        ----------
        paths : {"relative", "absolute"}
            How the scans' paths enter: those inside the session's folder relative to it
            (a scan folder moved or copied elsewhere keeps its fingerprint; the contents
            are fingerprinted apart), those outside it resolved; or every one resolved,
            as ingest results written before 2026-12-07 recorded them (review BG).
        """
        import hashlib
        import json

        def where(path: Path) -> str:
            # a scan outside the session's folder keeps its absolute path (review BH: a
            # relative one changed when the session alone was moved)
            if paths == "absolute" or not path.is_relative_to(self.folder):
                return str(path)
            return path.relative_to(self.folder).as_posix()

        doc = {
            "gravity": self.gravity_scanner.tolist(),
            "fiducials": self.expected_fiducials,
            "tumour_hint": None
            if self.tumour_hint_lps_mm is None
            else self.tumour_hint_lps_mm.tolist(),
            "reference": self.reference.name,
            "scans": [
                [s.name, where(s.path), s.posture_plane, s.posture_angle_deg] for s in self.scans
            ],
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def is_finite_number(value) -> bool:
    """``value`` is a finite int or float as read from TOML or JSON (a bool is no number).

    An integer beyond a float's range (TOML and JSON allow them) is not finite.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # review AY: np.isfinite raised a bare TypeError
        return False


def _vector(value, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != 3 or not all(map(is_finite_number, value)):
        raise SessionError(f"{where} must be a list of 3 numbers, got {value!r}")
    return np.asarray(value, dtype=float)


_KEYS = {
    "": {"scanner", "phantom", "landmarks", "scans", "source"},
    "scanner": {"gravity"},
    "phantom": {"density_kg_m3", "fiducials"},
    "landmarks": {"tumour"},
    "source": {"simulated", "generator"},
}

#: The longest ``[source] generator`` text (it is printed in reports).
MAX_GENERATOR_CHARS = 200


def _source(table: dict, toml: Path) -> dict:
    """``[source]`` checked: ``simulated`` a boolean, ``generator`` one short line of text."""
    simulated = table.get("simulated")
    if simulated is not None and not isinstance(simulated, bool):
        raise SessionError(
            f"{toml}: source.simulated must be true or false (whether the scans were "
            f"simulated rather than acquired), got {simulated!r}"
        )
    generator = table.get("generator")
    if generator is not None and (
        not isinstance(generator, str)
        or not generator.strip()
        or len(generator) > MAX_GENERATOR_CHARS
        or not generator.isprintable()
    ):
        raise SessionError(
            f"{toml}: source.generator must be one line of text of 1 to "
            f"{MAX_GENERATOR_CHARS} characters (what made the scans), got {generator!r}"
        )
    return {k: v for k, v in (("simulated", simulated), ("generator", generator)) if v is not None}


def _names(items, *, order: bool = True) -> str:
    """``a, b, c``: names for a message (review AX: Python's list reprs leaked into them)."""
    return ", ".join(sorted(items) if order else items)


def _table(doc: dict, key: str, where: Path) -> dict:
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise SessionError(f"{where}: [{key}] must be a table")
    unknown = set(value) - _KEYS[key]
    if unknown:
        raise SessionError(f"{where}: unknown key(s) {_names(unknown)} in [{key}]; "
                           f"expected {_names(_KEYS[key])}")  # fmt: skip
    return value


def _scan(entry, index: int, folder: Path, toml: Path) -> ScanEntry:
    where = f"{toml}: [[scans]] #{index + 1}"
    if not isinstance(entry, dict):
        raise SessionError(f"{where} must be a table")
    unknown = set(entry) - {"name", "path", "role", "posture"}
    if unknown:
        raise SessionError(
            f"{where}: unknown key(s) {_names(unknown)}; expected name, path, role, posture"
        )
    for key in ("name", "path", "role"):
        if key not in entry:  # review BG: it said "must be a non-empty string"
            raise SessionError(f"{where}: '{key}' is missing (a non-empty string)")
        if not isinstance(entry[key], str) or not entry[key]:
            raise SessionError(f"{where}: '{key}' must be a non-empty string, got {entry[key]!r}")
    if not NAME_PATTERN.fullmatch(entry["name"]):
        raise SessionError(
            f"{where}: name {entry['name']!r} must start with a letter or digit and hold only "
            "letters, digits, '.', '_' and '-' (it names folders and files in the work folder)"
        )
    if entry["name"].lower() in RESERVED_NAMES:  # review AW: WORK/scans/RUN is the marker
        raise SessionError(
            f"{where}: name {entry['name']!r} is taken by the run marker in WORK/scans/ "
            "(names are compared without case); choose another"
        )
    if entry["role"] not in ROLES:
        raise SessionError(
            f"{where}: role must be one of {_names(ROLES, order=False)}, got {entry['role']!r}"
        )
    path = (folder / entry["path"]).resolve()
    if not path.exists():
        raise SessionError(f"{where} ({entry['name']}): scan path {path} does not exist")
    if path.is_file() and not path.name.lower().endswith(VOLUME_SUFFIXES):
        from imaging.dicom import DICOM_SUFFIXES

        # review BG: found only when ingest read it, after the scans before it
        hint = (
            "a single DICOM file: point path at its series folder"
            if path.name.lower().endswith(DICOM_SUFFIXES)
            else "not a volume file: expected a DICOM series folder or a "
            f"{', '.join(VOLUME_SUFFIXES)} file"
        )
        raise SessionError(f"{where} ({entry['name']}): path {entry['path']!r} is {hint}")
    posture = entry.get("posture", {})
    if not isinstance(posture, dict):
        raise SessionError(f"{where}: posture must be an inline table")
    unknown = set(posture) - {"plane", "angle_deg"}
    if unknown:
        raise SessionError(
            f"{where}: unknown posture key(s) {_names(unknown)}; expected plane, angle_deg"
        )
    angle = posture.get("angle_deg")
    if angle is not None and not is_finite_number(angle):
        raise SessionError(f"{where}: posture.angle_deg must be a number, got {angle!r}")
    if angle is not None and abs(angle) > 360.0:  # review BG: 720 passed, matched nothing
        raise SessionError(
            f"{where}: posture.angle_deg must lie in [-360, 360] degrees, got {angle}"
        )
    plane = posture.get("plane")
    if plane is not None and plane not in PLANES:
        raise SessionError(
            f"{where}: posture.plane must be one of {_names(PLANES, order=False)}, got {plane!r}"
        )
    return ScanEntry(entry["name"], path, entry["role"], plane, angle)


def session_inputs(session: Session) -> list[Path]:
    """What a run over ``session`` reads: its folder and every scan's series or file."""
    return [session.folder, *(s.path for s in session.scans)]


#: Densities a phantom may declare, kg/m^3 (tissue and its phantoms lie near 1000;
#: the range refuses a density in g/cm^3 or g/mm^3 by mistake).
DENSITY_RANGE_KG_M3 = (500.0, 3000.0)


def checked_density_kg_m3(value, name: str) -> float:
    """A declared density (kg/m^3) as a float, refused outside :data:`DENSITY_RANGE_KG_M3`.

    Parameters
    ----------
    value : object
        The density as given.
    name : str
        Where it was given, for the message (``phantom.density_kg_m3``).

    Raises
    ------
    ValueError
        Not a number, or outside the range.
    """
    lo, hi = DENSITY_RANGE_KG_M3
    if isinstance(value, bool) or not (isinstance(value, numbers.Real) and lo <= value <= hi):
        raise ValueError(
            f"{name} must lie in [{lo:g}, {hi:g}] kg/m^3 (a tissue phantom's; 1.0 would be "
            f"g/cm^3), got {value!r}"
        )
    return float(value)


def load_session(folder: str | Path) -> Session:
    """Read and validate ``folder/session.toml``.

    Parameters
    ----------
    folder : str or Path
        The scans' folder, holding ``session.toml``.

    Returns
    -------
    Session
        The scans with their roles and postures, the scanner's unit gravity (LPS), the
        phantom's density (kg/m^3) and marker count, and the tumour hint.

    Raises
    ------
    SessionError
        Missing file, TOML syntax error, unknown roles, no or several reference scans,
        duplicate names, missing scan paths, malformed vectors.
    """
    folder = Path(folder).resolve()
    toml = folder / "session.toml"
    if not toml.is_file():
        raise SessionError(f"{folder}: no session.toml ({_where_a_session_is(folder)})")
    try:
        doc = tomllib.loads(toml.read_bytes().decode("utf-8-sig"))  # a leading BOM is dropped
    except UnicodeDecodeError as exc:
        raise SessionError(f"{toml}: not UTF-8 text (byte {exc.start}): save it as UTF-8") from exc
    except tomllib.TOMLDecodeError as exc:
        raise SessionError(f"{toml}: not valid TOML: {exc}") from exc
    unknown = set(doc) - _KEYS[""]
    if unknown:
        raise SessionError(f"{toml}: unknown table(s) {_names(unknown)}; "
                           f"expected {_names(_KEYS[''])}")  # fmt: skip
    scanner, phantom = _table(doc, "scanner", toml), _table(doc, "phantom", toml)
    landmarks = _table(doc, "landmarks", toml)
    source = _source(_table(doc, "source", toml), toml)
    g = _vector(scanner.get("gravity", [0.0, 1.0, 0.0]), f"{toml}: scanner.gravity")
    with np.errstate(over="ignore"):  # [1e308, 1e308, 0] was normalised to zeros
        length = np.linalg.norm(g)
    if not 0 < length < np.inf:
        raise SessionError(f"{toml}: scanner.gravity must be non-zero and of finite length")
    try:
        density = checked_density_kg_m3(
            phantom.get("density_kg_m3", DEFAULT_DENSITY_KG_M3), "phantom.density_kg_m3"
        )
    except ValueError as exc:
        raise SessionError(f"{toml}: {exc}") from None
    nfid = phantom.get("fiducials", 3)
    if not isinstance(nfid, int) or isinstance(nfid, bool) or not 3 <= nfid <= MAX_AUTO_MARKERS:
        # review AW: 8 were refused by the registration, after every scan was segmented
        raise SessionError(
            f"{toml}: phantom.fiducials must be an integer from 3 to {MAX_AUTO_MARKERS} (the "
            f"markers are matched between scans over every ordering), got {nfid!r}"
        )
    tumour = landmarks.get("tumour")
    hint = None if tumour is None else _vector(tumour, f"{toml}: landmarks.tumour")
    raw = doc.get("scans")
    if not isinstance(raw, list) or not raw:
        raise SessionError(f"{toml}: no [[scans]] entries")
    scans = tuple(_scan(e, i, folder, toml) for i, e in enumerate(raw))
    _check_scans(scans, toml)
    return Session(folder, g / np.linalg.norm(g), float(density), nfid, hint, scans, source)


def _check_scans(scans: tuple[ScanEntry, ...], toml: Path) -> None:
    names = [s.name.lower() for s in scans]  # review AC: WORK/scans/Left and /left are one
    twice = [names.count(n) > 1 for n in names]  # folder on macOS
    dup = sorted({s.name for s, t in zip(scans, twice, strict=True) if t})
    if dup:
        at = [f"#{i + 1}" for i, t in enumerate(twice) if t]
        raise SessionError(
            f"{toml}: duplicate scan name(s) {_names(dup)} in [[scans]] {', '.join(at)} (names "
            "are compared without case: they name folders of the work folder)"
        )
    refs = [(i, s.name) for i, s in enumerate(scans) if s.role == "reference"]
    if len(refs) != 1:
        found = ", ".join(f"{n} (#{i + 1})" for i, n in refs) if refs else "none"
        raise SessionError(f"{toml}: exactly one scan must have role 'reference', found {found}")
    by_path: dict[Path, list[str]] = {}
    for s in scans:
        by_path.setdefault(s.path, []).append(s.name)
    for path, same in by_path.items():
        if len(same) > 1:  # review AC: accepted without a word (no deformation between them)
            log.warning("%s: scans %s read the same data %s", toml, same, path)


def _find_scans(folder: Path) -> list[Path]:
    found = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):  # review AC: a hidden folder became the reference
            continue
        if p.is_dir() and any(f.is_file() and not f.name.startswith(".") for f in p.iterdir()):
            found.append(p)
        elif p.is_file() and p.name.lower().endswith(VOLUME_SUFFIXES):
            found.append(p)
    return found


def _unique_names(paths: list[Path]) -> list[str]:
    """Scan names from file names without volume suffixes, valid (:data:`NAME_PATTERN`), unique."""
    names = []
    for p in paths:
        stem = p.name
        for suf in sorted(VOLUME_SUFFIXES, key=len, reverse=True):
            if stem.lower().endswith(suf):
                stem = stem[: -len(suf)]
                break
        stem = re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip("._-") or "scan"
        name, k = stem, 2
        taken = {n.lower() for n in names} | RESERVED_NAMES  # as the session compares them
        while name.lower() in taken:
            name, k = f"{stem}_{k}", k + 1
        names.append(name)
    return names


def _sessions_below(folder: Path) -> list[Path]:
    """The folders directly inside ``folder`` that hold a ``session.toml``."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if (p / "session.toml").is_file())


def _where_a_session_is(folder: Path) -> str:
    """What to do about a folder without ``session.toml``, for the error (review AX)."""
    below = _sessions_below(folder)
    if below:  # a twin's OUT (its scans/ holds the session)
        return f"did you mean {below[0]}? it holds one"
    if (folder / "calibration.json").is_file() or any(folder.glob("scans/*/ingest.json")):
        return "this is a work folder: pass the scan folder it was made from"
    if any(folder.glob("*/ingest.json")):
        return "this is a work folder's scans/ (ingest's results): pass the scan folder"
    return "create one with `phantom-calib init`"


def scaffold_session(folder: str | Path, *, overwrite: bool = False) -> Path:
    """Write a ``session.toml`` listing every series folder and volume file in ``folder``.

    The first scan becomes the reference, the others calibration scans; edit the
    roles and postures afterwards.

    Parameters
    ----------
    folder : str or Path
        The folder that holds the scans' series folders or volume files.
    overwrite : bool
        Replace an existing ``session.toml``.

    Returns
    -------
    Path
        The ``session.toml`` written.

    Raises
    ------
    SessionError
        ``folder`` is not a folder, ``session.toml`` exists and not ``overwrite``,
        ``folder`` is a work folder (or its ``scans/``), a sub-folder holds a
        ``session.toml``, or no DICOM series folder or volume file is found.
    """
    import tomli_w

    from ..io import atomic_write

    folder = Path(folder)
    if not folder.is_dir():  # review BD: "[Errno 2] No such file or directory"
        raise SessionError(f"{folder}: no such folder (the scans' folder is expected)")
    target = folder / "session.toml"
    if target.exists() and not overwrite:
        raise SessionError(f"{target} exists; pass --overwrite (overwrite=True) to replace it")
    if any(folder.glob("scans/*/ingest.json")) or (folder / "calibration.json").is_file():
        # review AC: its calibration/, scans/ and validation/ were listed as series
        raise SessionError(
            f"{folder} is a work folder (ingest's or calibrate's results); point init at "
            "the folder that holds the scans' series"
        )
    if any(folder.glob("*/ingest.json")):  # review AX: its per-scan results became series
        raise SessionError(
            f"{folder} is a work folder's scans/ (ingest's results); point init at the "
            "folder that holds the scans' series"
        )
    below = _sessions_below(folder)
    if below:  # review AX: a twin's OUT gave scans/ and its sealed truth/ as two series
        raise SessionError(
            f"{below[0]} holds a session.toml: pass that folder (init lists the series "
            f"folders inside {folder}, and {below[0].name}/ is a scan folder, not a series)"
        )
    scans = _find_scans(folder)
    if not scans:
        raise SessionError(f"{folder}: no DICOM series folders or volume files found")
    names = _unique_names(scans)
    doc = {
        "scanner": {"gravity": [0.0, 1.0, 0.0]},
        "phantom": {"density_kg_m3": DEFAULT_DENSITY_KG_M3, "fiducials": 3},
        "scans": [
            {"name": n, "path": p.name, "role": "reference" if i == 0 else "calibration"}
            for i, (n, p) in enumerate(zip(names, scans, strict=True))
        ],
    }
    # what to edit, said where it is edited (review AX: init said "edit the roles and
    # postures" and wrote no posture, nor what the roles mean)
    text = (
        "# written by `phantom-calib init`: edit it before ingest (README, 'The scan folder').\n"
        "# roles: one reference (the posture the model geometry is taken from); calibration\n"
        "# scans fit c1; validation scans check it. Give each scan its nominal posture, e.g.\n"
        '# posture = { plane = "transverse", angle_deg = 25.0 }\n'
        "# and [phantom] fiducials the number of markers on the plate (3 to 7).\n"
    ) + tomli_w.dumps(doc)
    return atomic_write(target, lambda p: p.write_text(text))
