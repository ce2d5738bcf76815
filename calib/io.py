"""Atomic output files, run-level atomic output folders and provenance records."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import os
import platform
import sys
import threading
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path

from fem.io import atomic_write

log = logging.getLogger(__name__)

__all__ = [
    "OUT_OPTION",
    "WORK_OPTION",
    "ForeignFolderError",
    "InsideRunFolderError",
    "RunOutputs",
    "StaleOutputError",
    "WorkBusyError",
    "atomic_write",
    "check_not_in_run_folder",
    "check_out_file",
    "check_out_folder",
    "check_replaceable",
    "check_run",
    "clean_stale",
    "file_sha256",
    "input_records",
    "locking_work",
    "provenance",
    "run_id_of",
    "source_sha256",
    "work_lock",
    "write_json_atomic",
]

#: Distributions whose versions a provenance record names (None where not installed:
#: open3d is ``open3d-cpu`` on x86_64 and ``open3d`` elsewhere; pypardiso decides between
#: PARDISO and SuperLU, and mkl's version sets PARDISO's last bits; the readers and
#: segmentation of ingest; torch the surrogates'; zarr the sweep store's). Review BI: mkl,
#: the ingest chain, torch and zarr were missing.
_PACKAGES = (
    *("phantom-calib", "numpy", "scipy", "scikit-fem", "tetgen", "meshio"),
    *("open3d-cpu", "open3d", "pypardiso", "mkl"),
    *("SimpleITK", "pydicom", "python-gdcm", "nibabel", "pynrrd", "scikit-image", "trimesh"),
    *("torch", "zarr"),
)


def write_json_atomic(path: str | os.PathLike, data: dict) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    text = json.dumps(data, indent=2, sort_keys=False, allow_nan=False)
    return atomic_write(path, lambda p: p.write_text(text + "\n"))


#: How the output checks name the option they check: a Python parameter, then the
#: command's flag (review BW, F6; review BZ, F4: ingest and calibrate take ``work``).
OUT_OPTION = "out (--out)"
WORK_OPTION = "work (--out)"


def _check_writable(out: Path, folder: Path, option: str) -> None:
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"{option} {out}: {folder} is not writable")


def _check_parents(out: Path, option: str) -> None:
    """The nearest existing path above ``out`` must be a writable folder."""
    parent = next((p for p in out.parents if p.exists()), Path("."))
    if not parent.is_dir():
        raise NotADirectoryError(f"{option} {out}: {parent} is a file, not a folder")
    _check_writable(out, parent, option)


def check_work_writable(work: str | os.PathLike, writes: str) -> None:
    """Refuse a work folder the command cannot write into, before its work.

    ``writes`` names what it writes there (for the message). A read-only WORK was found
    only when ``validate`` or ``diagnose`` had done all their work (review AC).
    """
    if not os.access(work, os.W_OK | os.X_OK):
        raise PermissionError(f"{work}: not writable (this command writes {writes} there)")


#: A work folder's run folders, the record beside each, and the command that replaces it
RUN_FOLDERS = {
    "scans": ("ingest_summary.json", "ingest"),
    "calibration": ("calibration.json", "calibrate"),
    "validation": ("validation.json", "validate"),
    "diagnosis": ("diagnosis.json", "diagnose"),
}


class InsideRunFolderError(ValueError):
    """An ``--out`` inside a work folder's run folder, which a later run replaces whole."""


class ForeignFolderError(FileExistsError):
    """A run folder's place in WORK (``calibration/``, ...) holds something no run wrote."""


def check_replaceable(
    work: str | os.PathLike,
    folders,
    *,
    option: str = WORK_OPTION,
    command: str | None = None,
) -> None:
    """Refuse a WORK whose run folders a command would replace but no run wrote, before work.

    A run swaps its folder in whole (:class:`RunOutputs`): whatever ``WORK/calibration/``
    held went with it. A folder is a run's where it has a ``RUN`` marker or its record
    lies beside it (``calibration.json``: an interrupted run, or one of an older version);
    an empty folder loses nothing. Anything else there — a user's own ``calibration/``
    folder of notes, a file of that name — is refused (review CG-7: it was deleted
    without a word), and so is a link of that name (the run would put a folder in its
    place; what it links to was never touched). Files a user adds inside a run's folder
    go with the next run of its command (README).

    Parameters
    ----------
    work : path-like
    folders : iterable of str
        The run folders the command writes (keys of :data:`RUN_FOLDERS`).
    option : str
        How the message names WORK (``"WORK"`` for a command that takes it as argument).
    command : str, optional
        The command the user ran, where it is not the folder's own (``calibrate``
        ingests first); default: the folder's command.

    Raises
    ------
    ForeignFolderError
    """
    work = Path(work)
    for name in folders:
        path, (record, own) = work / name, RUN_FOLDERS[name]
        if not (path.exists() or path.is_symlink()):
            continue
        said = command or own
        if path.is_symlink():
            raise ForeignFolderError(
                f"{option} {work}: {path} is a link (to {os.readlink(path)}); `phantom-calib "
                f"{said}` writes {name}/ as a folder of its own in its place: remove the "
                f"link or choose another {option}"
            )
        if path.is_dir():
            if (path / "RUN").is_file() or (work / record).is_file() or not any(path.iterdir()):
                continue
            what = f"a folder no phantom-calib run wrote (no RUN marker, no {record} beside it)"
        else:
            what = "a file"
        raise ForeignFolderError(
            f"{option} {work}: {path} is {what}; `phantom-calib {said}` replaces "
            f"{name}/ as a whole, so it would be lost: move it away or choose another {option}"
        )


def check_not_in_run_folder(out: str | os.PathLike, *, option: str = OUT_OPTION) -> None:
    """Refuse an ``--out`` inside a work folder's ``calibration/``, ``validation/``, ...

    Each run replaces its folder as a whole (review AT: a sweep store written into
    ``WORK/calibration/`` went with the next ``calibrate``, without a word).

    Raises
    ------
    InsideRunFolderError
    """
    out = Path(out).resolve()  # links followed, ".." taken out (review AU: both fooled it)
    for folder in (out, *out.parents):
        record, command = RUN_FOLDERS.get(folder.name, (None, None))
        if record is not None and (folder.parent / record).is_file():
            raise InsideRunFolderError(
                f"{option} {out}: inside {folder}, which the next `phantom-calib {command}` of "
                f"{folder.parent} replaces as a whole; write it outside"
            )


def check_out_file(out: str | os.PathLike, *, option: str = OUT_OPTION) -> None:
    """Refuse an ``--out`` file that cannot be written, before any work.

    Raises
    ------
    IsADirectoryError
        ``out`` is a folder.
    NotADirectoryError
        Its nearest existing parent is a file.
    PermissionError
        Its nearest existing parent folder is not writable.
    InsideRunFolderError
        It lies in a work folder's run folder (:func:`check_not_in_run_folder`).
    """
    out = Path(out)
    check_not_in_run_folder(out, option=option)
    if out.is_dir():
        raise IsADirectoryError(f"{option} {out}: is a folder; name the file to write")
    _check_parents(out, option)


def check_out_folder(out: str | os.PathLike, *, option: str = OUT_OPTION) -> None:
    """Refuse an output folder that cannot be written, before any work.

    Raises
    ------
    NotADirectoryError
        ``out``, or its nearest existing parent, is a file.
    FileExistsError
        ``out`` is a link to nothing.
    PermissionError
        ``out``, or where it does not exist its nearest existing parent, is not writable.
    InsideRunFolderError
        It lies in a work folder's run folder (:func:`check_not_in_run_folder`).
    """
    out = Path(out)
    check_not_in_run_folder(out, option=option)
    if out.is_symlink() and not out.exists():
        raise FileExistsError(f"{option} {out}: a link to nothing ({os.readlink(out)})")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{option} {out}: exists and is not a folder")
    if out.exists():
        _check_writable(out, out, option)
    else:
        _check_parents(out, option)


def check_out_apart(
    out: str | os.PathLike, inputs, *, what: str = "the input", option: str = OUT_OPTION
) -> None:
    """Refuse an output folder that is, or holds, one of the ``inputs``, before any work.

    A run replaces its folders under ``out`` (``scans/``, ``calibration/``, ...) as a
    whole: an input inside ``out`` would be deleted (``ingest SCANS --out`` SCANS' parent
    removed the scan data), and ``out`` equal to an input mixes outputs into it.

    Parameters
    ----------
    out : path-like
        The output folder.
    inputs : iterable of path-like
        The folders and files the run reads.
    what : str
        What the inputs are, for the message.

    Raises
    ------
    ValueError
        ``out`` is one of the inputs or holds one.
    """
    o = Path(out).resolve()
    for p in inputs:
        q = Path(p).resolve()
        if q == o or o in q.parents:
            where = "is" if q == o else "holds"
            raise ValueError(
                f"{option} {out} {where} {what} {p}: each run replaces its folders under it "
                "as a whole, so it would delete or mix into the input; choose an output "
                "folder outside it (e.g. next to it)"
            )


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def source_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a scan source: a file's bytes, or a folder's files (names and bytes).

    Hidden files are ignored; files are taken in sorted order, so the fingerprint does
    not depend on the file system's listing order.
    """
    path = Path(path)
    if path.is_file():
        return file_sha256(path)
    h = hashlib.sha256()
    for f in sorted(p for p in path.rglob("*") if p.is_file() and not p.name.startswith(".")):
        h.update(str(f.relative_to(path)).encode())
        h.update(bytes.fromhex(file_sha256(f)))
    return h.hexdigest()


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


#: Environment variables that set the thread counts (the FE results are reproducible to
#: round-off at equal counts, bitwise for one sequence of solves: README)
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _source_revision(root: Path | None = None) -> dict | None:
    """The git commit of the source tree this package runs from, and whether it has edits.

    ``{"commit": SHA, "uncommitted_edits": bool}``, and where there are edits to tracked
    files, ``"edits_sha256"``: the digest of ``git diff HEAD --binary`` (with the options
    that fix its text whatever the user's git settings), so that two runs of the same
    edited tree can be told to be the same code (review BT, F12); without it where that
    diff fails (the edits are then taken to differ). None where it is
    not a git checkout (an installed wheel) or git is missing. Asked at every record
    (review BI: a cached answer kept a long-lived kernel's first commit and edits after the
    tree changed under it).
    """
    import hashlib
    import subprocess

    root = Path(__file__).resolve().parent.parent if root is None else root
    if not (root / ".git").exists():
        return None
    try:
        git = ["git", "--no-optional-locks", "-C", str(root)]  # no index.lock (review AP)
        commit = subprocess.run(
            [*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        edits = subprocess.run(
            [*git, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    out = {"commit": commit, "uncommitted_edits": bool(edits)}
    if edits:  # review BV, F3: a digest the user's diff settings (a tool, colour) leave alone
        fixed = ["--binary", "--no-ext-diff", "--no-textconv", "--no-color", "--no-renames"]
        fixed += ["--diff-algorithm=myers", "--src-prefix=a/", "--dst-prefix=b/"]
        try:
            diff = subprocess.run(
                [*git, "diff", *fixed, "HEAD"], capture_output=True, timeout=60, check=True
            ).stdout
        except (OSError, subprocess.SubprocessError):  # F4: still a checkout, with edits
            return out
        out["edits_sha256"] = hashlib.sha256(diff).hexdigest()
    return out


def _thread_pools() -> dict:
    """The thread counts in use: ``cpu_count`` and each loaded BLAS/OpenMP pool's.

    Review BI: ``threads`` records the environment variables only, null where unset,
    when MKL and OpenMP take every core; the FE results' last bits depend on the counts
    in use. ``pools`` maps each library loaded so far, by threadpoolctl's ``prefix``
    (``libmkl_rt``, ``libscipy_openblas``, ``libgomp``, ``libiomp``, ...), to its
    ``internal_api`` and largest ``num_threads`` (review BK: keyed by the API, MKL's and
    torch's OpenMP runtimes were one entry).
    """
    from threadpoolctl import threadpool_info

    pools: dict[str, dict] = {}
    for lib in threadpool_info():
        entry = pools.setdefault(
            str(lib.get("prefix")), {"api": str(lib.get("internal_api")), "num_threads": 0}
        )
        entry["num_threads"] = max(entry["num_threads"], int(lib.get("num_threads") or 0))
    return {"cpu_count": os.cpu_count(), "pools": dict(sorted(pools.items()))}


def input_records(inputs: dict[str, str | os.PathLike]) -> dict[str, dict]:
    """Each input file's absolute ``path`` and ``sha256``, taken now.

    Take them when the inputs are read and give them to :func:`provenance` (review BI: a
    record hashed at the end of a long run claimed the bytes of an input edited during
    it, and called results of the old bytes current).

    Parameters
    ----------
    inputs : dict of str to path
        Files by the names the record gives them.

    Returns
    -------
    dict of str to dict
        ``{"path": absolute path, "sha256": hex digest}`` per name.

    Raises
    ------
    FileNotFoundError
        An input is missing.
    """
    return {
        k: {"path": str(Path(v).resolve()), "sha256": file_sha256(v)} for k, v in inputs.items()
    }


def _entry() -> str:
    """How this process was started: ``phantom-calib``, ``jupyter kernel`` or ``python``.

    Review BI: in a notebook ``command`` (``sys.argv``) is the kernel's launcher and its
    connection file, which runs nothing again; ``entry`` tells a reader so. ``python`` is
    a script (``command`` is then its path and arguments) or an interactive interpreter.
    """
    argv0 = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
    main = sys.modules.get("__main__")
    if argv0 == "phantom-calib" or getattr(main, "__package__", None) == "calib":
        return "phantom-calib"
    if "ipykernel" in sys.modules or argv0 == "ipykernel_launcher.py":
        return "jupyter kernel"
    return "python"


def provenance(
    *, inputs: dict[str, str | os.PathLike | dict] | None = None, parameters=None
) -> dict:
    """A provenance record: time, versions, input file hashes and parameters.

    ``inputs`` maps names to paths (hashed now) or to :func:`input_records` entries
    (hashed when they were read).

    Paths are absolute and the working folder is recorded, so that the command can be
    run again from the record (review AN); ``entry`` says whether ``command`` is
    ``phantom-calib``'s, a script's or a Jupyter kernel's launcher (:func:`_entry`);
    ``source`` is the git commit the package runs from (None outside a checkout),
    ``threads`` the thread-count variables,
    ``thread_pools`` the counts in use (:func:`_thread_pools`).
    """
    return {
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "versions": {p: _version(p) for p in _PACKAGES},
        "source": _source_revision(),
        "command": sys.argv,
        "entry": _entry(),
        "cwd": os.getcwd(),
        "threads": {k: os.environ.get(k) for k in _THREAD_VARIABLES},
        "thread_pools": _thread_pools(),
        "inputs": {
            k: v if isinstance(v, dict) else input_records({k: v})[k]
            for k, v in (inputs or {}).items()
        },
        "parameters": parameters or {},
    }


class StaleOutputError(RuntimeError):
    """A result folder and its record are not from the same run (an interrupted write)."""


class WorkBusyError(RuntimeError):
    """Another phantom-calib command is writing this work folder."""


#: Work folders this process holds the lock of, with the holding thread and command
_HELD: dict[Path, tuple[int, str]] = {}
_HELD_GUARD = threading.Lock()


@contextlib.contextmanager
def work_lock(work: str | os.PathLike, command: str):
    """Hold ``WORK/.lock`` for the whole of one command that writes WORK.

    ``ingest``, ``calibrate``, ``validate`` and ``diagnose`` each hold it, so that two of
    them never write one WORK at once (review AN: an ingest during a calibration left a
    ``calibration.json`` naming scans it never fitted, and a validate beside a
    calibration replaced the new validation with the old fit's). The lock is an
    ``flock`` on an open file: the system releases it when its process ends, however it
    ends; the file is removed when the command ends (one killed leaves it, unlocked).
    Re-entrant within a thread (calibrate's own ingest); another thread of the same
    process is refused as another process is. ``work`` must exist
    (:func:`locking_work` makes it where the command would).

    Raises
    ------
    WorkBusyError
        Another process or thread holds the lock (its command, and its process id, are
        named).
    """
    work = Path(work).resolve()
    me = threading.get_ident()
    with _HELD_GUARD:
        holder = _HELD.get(work)
    if holder is not None and holder[0] == me:  # the outer command releases it
        yield
        return
    if holder is not None:  # flock would let this process's second thread through
        raise WorkBusyError(
            f"{work}: in use by another phantom-calib command of this process "
            f"({holder[1]}, another thread); run this one when it has finished"
        )
    path = work / ".lock"
    f = _locked_file(path, work)
    if f is None:
        yield
        return
    f.seek(0)
    f.truncate()
    f.write(f"{command}, process {os.getpid()}\n")
    f.flush()
    with _HELD_GUARD:
        _HELD[work] = (me, command)
    try:
        # no other command writes WORK now: what a killed one of any kind left goes (review
        # AN: a killed calibrate's staging folder stayed until the next calibrate's commit)
        clean_stale(work, WORK_OUTPUTS)
        yield
    finally:
        with _HELD_GUARD:
            _HELD.pop(work, None)
        path.unlink(missing_ok=True)  # before the release: no output folder keeps it
        f.close()


def _locked_file(path: Path, work: Path):
    """``path`` open and exclusively ``flock``-ed, or None where nothing can lock (said).

    Raises
    ------
    WorkBusyError
        Another process holds it.
    PermissionError
        ``work`` is not writable.
    """
    try:
        import fcntl
    except ImportError:  # Windows: no flock (review AP)
        log.warning("%s: not locked (no fcntl here): run one command at a time", work)
        return None
    while True:
        try:
            f = open(path, "a+")  # held open for the command's life
        except PermissionError as exc:
            raise PermissionError(f"{work}: not writable (this command writes there)") from exc
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "a process"
            f.close()
            raise WorkBusyError(
                f"{work}: in use by another phantom-calib command ({holder}); run this one "
                "when it has finished"
            ) from None
        except OSError as exc:  # a file system without flock (some NFS, CIFS mounts)
            f.close()
            path.unlink(missing_ok=True)
            log.warning("%s: not locked (%s): run one command at a time", work, exc)
            return None
        try:  # the file its holder removed on release is not the lock: open it again
            if os.stat(path).st_ino == os.fstat(f.fileno()).st_ino:
                return f
        except FileNotFoundError:
            pass
        f.close()


def locking_work(command: str, *, create: bool = False):
    """Decorate a workflow whose ``work`` argument it writes: it runs under :func:`work_lock`.

    Parameters
    ----------
    command : str
        Named in the lock file, for the message another command gets.
    create : bool
        Make a missing WORK (its parents too) for the lock, after
        :func:`check_out_folder` accepts it, and remove what was made again if the command
        leaves it empty (a refused input leaves no folder). Without it
        a missing WORK is not locked: the command fails on reading it.
    """
    import inspect

    def decorate(fn):
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def run(*args, **kwargs):
            work = Path(signature.bind(*args, **kwargs).arguments["work"])
            made = []
            if create and not work.exists():
                check_out_folder(work, option=WORK_OPTION)
                made = [p for p in (work, *work.parents) if not p.exists()]
                work.mkdir(parents=True, exist_ok=True)  # a racing command: the lock decides
            if not work.is_dir():
                return fn(*args, **kwargs)
            try:
                with work_lock(work, command):
                    return fn(*args, **kwargs)
            finally:
                for p in made:  # deepest first
                    try:
                        p.rmdir()
                    except OSError:
                        break

        return run

    return decorate


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` lives; a number no process can have counts as alive."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def _dir_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o777 & ~mask


#: The outputs the commands that hold the WORK lock write there (folder, record), whose
#: temporaries a killed run leaves: ingest, calibrate, validate, diagnose.
WORK_OUTPUTS = tuple(
    name for folder, (record, _) in RUN_FOLDERS.items() for name in (folder, record)
)


def clean_stale(work: Path, names: tuple[str, ...]) -> list[Path]:
    """Remove temporary entries left in ``work`` by killed runs; return what was removed.

    Staging folders ``.NAME.staging-PID``, replaced folders ``.NAME.old-PID`` and
    ``.NAME.partial-PID`` of the given output names whose process is no longer alive, and
    the atomic writes' temporary files of the names that are files (``.STEM.*.tmp.SUFFIX``
    of ``STEM.SUFFIX``: another file of that stem, a ``calibration.png`` beside the
    ``calibration`` folder, is not one of them). An entry that cannot be removed stays.
    """
    import re
    import shutil

    removed = []
    if not work.is_dir():
        return removed
    stems = {Path(n).stem for n in names} | set(names)
    files = [Path(n) for n in names if Path(n).suffix]
    for entry in work.iterdir():
        m = re.fullmatch(r"\.(.+)\.(staging|old|partial)-(\d+)", entry.name)
        if m and m.group(1) in stems and not _pid_alive(int(m.group(3))):
            try:
                shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
            except OSError as exc:
                log.warning("%s: left by a killed run, not removable (%s)", entry, exc)
                continue
            removed.append(entry)
            continue
        name = entry.name
        if any(name.startswith(f".{f.stem}.") and name.endswith(f".tmp{f.suffix}") for f in files):
            if entry.is_file():
                entry.unlink(missing_ok=True)
                removed.append(entry)
    return removed


class RunOutputs:
    """One run's outputs, staged apart and swapped in as a whole.

    A command writes a folder of outputs (``WORK/calibration/``) and a record
    (``WORK/calibration.json``). Files go into a staging folder
    (``WORK/.calibration.staging-PID``); :meth:`commit` then removes the old record,
    swaps the folders by renames and writes the new record last, with a ``run_id`` that
    the folder's ``RUN`` file repeats. Killed at any point, WORK holds either the old
    run (record and folder), or the new one, or a folder with no record (no result):
    never a record beside another run's files. :func:`check_run` tells them apart for
    readers; stale staging folders are removed at the next start.

    Parameters
    ----------
    work : path
    folder : str
        Name of the output folder inside ``work``.
    record : str
        Name of the record file inside ``work`` (written last).
    """

    def __init__(self, work: str | os.PathLike, *, folder: str, record: str):
        self.work = Path(work)
        self.folder, self.record = folder, record
        if folder in RUN_FOLDERS:  # the commands check first; this is the last guard
            check_replaceable(self.work, (folder,))
        self.work.mkdir(parents=True, exist_ok=True)
        clean_stale(self.work, (folder, record))
        pid = os.getpid()
        self.stage = self.work / f".{folder}.staging-{pid}"
        import shutil

        shutil.rmtree(self.stage, ignore_errors=True)
        self.stage.mkdir(mode=_dir_mode())
        self.run_id = f"{datetime.now(UTC).strftime('%Y%m%dT%H%M%S.%fZ')}-{pid}"

    def path(self, name: str) -> Path:
        """Where to write ``name`` of the output folder (inside the staging folder)."""
        return self.stage / name

    def commit(self, record: dict) -> dict:
        """Swap the staged folder in and write the record (with ``run_id``) last."""
        import shutil

        write_json_atomic(self.stage / "RUN", {"run_id": self.run_id})
        target, record_path = self.work / self.folder, self.work / self.record
        record_path.unlink(missing_ok=True)
        old = self.work / f".{self.folder}.old-{os.getpid()}"
        if target.exists():
            os.replace(target, old)
        os.replace(self.stage, target)
        doc = {"run_id": self.run_id} | record
        write_json_atomic(record_path, doc)
        shutil.rmtree(old, ignore_errors=True)
        return doc

    def abort(self) -> None:
        """Remove the staging folder (the previous outputs stay as they were)."""
        import shutil

        shutil.rmtree(self.stage, ignore_errors=True)

    def __enter__(self) -> RunOutputs:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.stage.exists():
            self.abort()


def run_id_of(folder: str | os.PathLike) -> str | None:
    """The run id a result folder's ``RUN`` marker holds; None where it has none.

    Raises
    ------
    StaleOutputError
        ``RUN`` is not a run marker.
    """
    run = Path(folder) / "RUN"
    if not run.is_file():
        return None
    try:
        return json.loads(run.read_text()).get("run_id")
    except (json.JSONDecodeError, AttributeError) as exc:
        raise StaleOutputError(f"{run}: not a run marker ({exc})") from exc


def check_run(work: str | os.PathLike, *, folder: str, record: str) -> dict:
    """Read a run's record and check that its folder is from the same run.

    Raises
    ------
    FileNotFoundError
        No record (the command never finished here).
    StaleOutputError
        The folder's ``RUN`` differs from the record's ``run_id``.
    """
    work = Path(work)
    path = work / record
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise StaleOutputError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(doc, dict):
        raise StaleOutputError(
            f"{path}: expected a JSON object (the command's record), got {type(doc).__name__}"
        )
    if "run_id" in doc:
        if run_id_of(work / folder) != doc["run_id"]:
            raise StaleOutputError(
                f"{work / folder} is not from the run recorded in {path} (an interrupted "
                "run?); run the command again"
            )
    return doc
