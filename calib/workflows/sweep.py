"""``phantom-calib sweep`` and ``surrogate``: the only code that writes a SWEEP folder.

:func:`run_sweep` solves a calibrated work folder's model over a plan of gravity
directions and c1 values into a Zarr store (format: :mod:`calib.sweep.store`);
re-running it resumes. :func:`run_surrogate_train` fits an :mod:`nn` surrogate on a
store and :func:`run_surrogate_predict` writes one prediction as a mesh.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from nn.device import Device

from ..choices import PredictFrame, SurrogateKind

__all__ = [
    "SweepOptions",
    "run_surrogate_predict",
    "run_surrogate_train",
    "run_sweep",
]

log = logging.getLogger(__name__)

_BACKENDS = ("serial", "pool", "dask")
#: ``--dask``: ``local``, or a scheduler address ``[tcp://|tls://]HOST:PORT`` (IPv6 in [])
_DASK_ADDRESS = re.compile(r"(?:(?:tcp|tls)://)?(?:\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+):(\d{1,5})")
_KINDS = get_args(SurrogateKind)
_PREDICT_SUFFIXES = (".vtu", ".ply")


@dataclass(frozen=True)
class SweepOptions:
    """Options of ``phantom-calib sweep`` (see its ``--help``).

    Every option that needs no file (backend, counts, the form of the ``dask``
    address, the plan, c1 axis and hold-out) is checked at construction, so a bad one
    fails before anything is read or written; the c1 axis again against the calibration
    it reads (a sliding model's springs).

    Attributes
    ----------
    plan : str
        ``dissertation``, ``dissertation:transverse`` or ``sphere:N``
        (:func:`calib.sweep.make_plan`).
    c1_axis : str or None
        ``LO:HI:N`` in Pa, or None for the calibrated c1 alone.
    holdout : float
        Fraction of a sphere plan's directions held out for validation.
    seed : int
        Seed of the hold-out.
    backend : {"serial", "pool", "dask"}
    workers : int or None
        Processes of the pool or of a local Dask cluster (None: 2); not with ``serial``
        nor with a scheduler's address (its workers are its own).
    dask : str or None
        ``local`` or ``tcp://HOST:PORT`` (backend ``dask`` only).
    chunk_size : int
        Scenarios per continuation chunk.
    max_angle_deg : float
        Farthest warm start (see :func:`calib.sweep.plan_continuation`).
    threads : int
        Threads of each pool worker (the serial backend keeps its process's).
    overwrite : bool
        Replace the store at ``out``, whatever it holds: its solved scenarios are lost
        (without it a store of this model and plan is resumed, another refused).
    retry_failed : bool
        Solve the scenarios recorded as failed again.
    """

    plan: str = "dissertation"
    c1_axis: str | None = None
    holdout: float = 0.0
    seed: int = 0
    backend: Literal["serial", "pool", "dask"] = "pool"
    workers: int | None = None
    dask: str | None = None
    chunk_size: int = 12
    max_angle_deg: float = 45.0
    threads: int = 1
    overwrite: bool = False
    retry_failed: bool = False

    def __post_init__(self) -> None:
        """Check the options that need no file, so that a bad one fails before any work.

        Raises
        ------
        ValueError
            An unknown backend, fewer than 1 worker, thread or scenario per chunk, a
            ``max_angle_deg`` outside [0, 180] (or NaN), or a
            ``dask`` that is neither ``local`` nor a ``tcp://HOST:PORT`` address (its
            form only: whether a scheduler answers there is known when it is reached).
        calib.sweep.PlanError
            A plan, c1 axis or hold-out that no calibration can make valid (an unknown
            plan, ``LO:HI:N`` out of form, a hold-out outside [0, 1) or on the
            dissertation's plan), found before the work folder is read (review BD).
        """
        from ..sweep import make_plan

        # the calibrated c1 only fills a plan without a c1 axis: any positive stand-in
        # checks everything else about the plan
        make_plan(
            self.plan, c1_cal_pa=1.0, c1_axis=self.c1_axis, holdout=self.holdout, seed=self.seed
        )
        if self.backend not in _BACKENDS:
            raise ValueError(f"unknown backend {self.backend!r}; choose serial, pool or dask")
        if self.backend == "serial" and self.workers is not None:  # review AT, AU: ignored
            raise ValueError(
                "backend 'serial' (--serial) solves in this process: drop workers (--workers)"
            )
        for name, value in (
            ("workers (--workers)", 2 if self.workers is None else self.workers),
            ("chunk_size (--chunk-size)", self.chunk_size),
            ("threads", self.threads),
        ):
            if not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.dask is not None and self.dask != "local":
            m = _DASK_ADDRESS.fullmatch(self.dask)
            if m is None or not 1 <= int(m.group(1)) <= 65535:
                raise ValueError(
                    f"dask (--dask) must be 'local' or a scheduler address tcp://HOST:PORT, "
                    f"got {self.dask!r}"
                )
        if not 0.0 <= float(self.max_angle_deg) <= 180.0:  # review BK: NaN was accepted
            raise ValueError(
                f"max_angle_deg must be an angle in [0, 180] degrees, got {self.max_angle_deg!r}"
            )
        if self.dask is not None and self.backend != "dask":  # review AW: it was ignored
            raise ValueError(f"dask (--dask) goes with backend 'dask', not {self.backend!r}")
        if self.dask not in (None, "local") and self.workers is not None:
            raise ValueError(
                f"workers (--workers) sizes a LocalCluster (dask 'local'); the scheduler at "
                f"{self.dask} has its own workers: drop workers (--workers)"
            )


#: The sweep's backends, whose versions its records add to :func:`calib.io.provenance`'s
_BACKEND_PACKAGES = ("dask", "distributed", "threadpoolctl")


def _provenance(**kw) -> dict:
    """:func:`calib.io.provenance` with the versions of the sweep's backends too."""
    from ..io import _version, provenance

    prov = provenance(**kw)
    prov["versions"] |= {p: _version(p) for p in _BACKEND_PACKAGES}
    return prov


def _has_distributed() -> bool:
    return importlib.util.find_spec("distributed") is not None


def _is_store(path: Path) -> bool:
    import json

    meta = path / "zarr.json"
    try:
        return json.loads(meta.read_text()).get("attributes", {}).get("format") is not None
    except (OSError, ValueError):
        return False


def _create_store(
    out: Path, model, plan, cont, n_dofs: int, opts: SweepOptions, prov: dict, *, replacing: bool
):
    """Build the empty store beside ``out`` and move it into place when complete.

    ``replacing``: the caller holds the lock of the store at ``out`` and replaces it
    (``--overwrite``). Otherwise ``out`` must still be absent or empty when the new store
    moves in: a store another sweep made there meanwhile is never replaced (review BT:
    it was, and that sweep then wrote its scenarios into this store).
    """
    import errno

    from ..sweep.store import StoreError, SweepStore

    stage = out.parent / f".{out.name}.staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    try:
        SweepStore.create(
            stage,
            model,
            plan,
            cont,
            n_dofs=n_dofs,
            chunk_size=opts.chunk_size,
            max_angle_deg=opts.max_angle_deg,
            provenance=prov,
        )
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)  # a half-written store goes with it
        raise
    if replacing and out.exists() and any(out.iterdir()):  # the old store goes only now
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
        try:
            os.replace(stage, out)
        except BaseException:
            os.replace(old, out)  # the old store back in place
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        try:  # onto nothing or an empty folder; a folder filled meanwhile refuses it
            os.replace(stage, out)
        except OSError as exc:
            shutil.rmtree(stage, ignore_errors=True)
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            raise StoreError(
                f"out (--out) {out}: a store appeared there while this one was being created "
                "(another sweep with the same out?); it is left as it is: run again to "
                "resume it, or with overwrite (--overwrite) to replace it"
            ) from exc
    return SweepStore.open(out)


def _summary(store, backend_info: dict, run: dict, wall_s: float) -> dict:
    from ..sweep.store import FAILED, SOLVED

    status = store.status()
    conv = np.asarray(store.group["results/convergence"][:])
    col = {c: k for k, c in enumerate(store.attrs["convergence_columns"])}
    ok = status == SOLVED
    warm = ok & (conv[:, col["warm_start"]] == 1)
    cold = ok & ~warm

    def stats(mask) -> dict:
        it = conv[mask, col["newton_iterations"]]
        wall = conv[mask, col["wall_s"]]
        if not it.size:
            return {"n": 0}
        return {
            "n": int(it.size),
            "newton_mean": float(it.mean()),
            "newton_median": float(np.median(it)),
            "newton_max": int(it.max()),
            "wall_s_median": float(np.median(wall)),
        }

    return {
        "solved": int(ok.sum()),
        "failed": int((status == FAILED).sum()),
        "pending": int((status == 0).sum()),
        "n_scenarios": int(len(status)),
        "this_run": {
            "solved": run["solved"],
            "failed": run["failed"],
            "retried_after_lost_worker": run["retried"],
            "wall_s": wall_s,
        }
        | backend_info,
        "warm": stats(warm),
        "cold": stats(cold),
        "solve_wall_s_total": float(np.nansum(conv[ok, col["wall_s"]])),
        "solve_cpu_s_total": float(np.nansum(conv[ok, col["cpu_s"]])) if "cpu_s" in col else None,
    }


def run_sweep(work, out, options: SweepOptions | None = None, *, progress=None) -> dict:
    """Solve a calibrated model over a plan; write (or resume) the store ``out``.

    Parameters
    ----------
    work : path
        Calibrated work folder (``calibration.json`` and ``calibration/``).
    out : path
        Store folder (created, or resumed when it holds this model's and plan's sweep).
    options : SweepOptions, optional
    progress : callable, optional
        Called with a dict after each committed scenario, and once with
        ``{"total": S_pending, "done": 0, "start": True}`` before the first.

    Returns
    -------
    dict
        The run's summary (also stored in the store's ``summary`` attribute).

    Raises
    ------
    calib.sweep.CalibrationMissingError
        ``work`` has no calibration.
    calib.sweep.store.StoreError
        ``out`` is not a store, a store of another model or plan, or locked.
    RuntimeError
        The dask backend without dask.distributed installed (checked first), or a
        backend that cannot start (no scheduler at ``options.dask``): started before a
        store or folder is made, so nothing is created and an old store under
        ``overwrite`` stays.

    Notes
    -----
    The options themselves are checked when :class:`SweepOptions` is built, before
    anything is read or written.
    """
    from ..io import check_out_folder, clean_stale
    from ..sweep import PlanError, load_sweep_model, make_plan, plan_continuation
    from ..sweep.engine import make_backend, run_scenarios
    from ..sweep.store import FAILED, PENDING, SOLVED, StoreError, SweepStore

    opts = options or SweepOptions()  # SweepOptions checks itself when built
    t0 = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise StoreError(f"out (--out) {out}: exists and is not a folder")
    check_out_folder(out)
    if opts.backend == "dask" and not _has_distributed():
        raise RuntimeError(
            "the dask backend needs dask.distributed: pip install 'phantom-calib[sweep]'"
        )
    model = load_sweep_model(work)
    if model.reference_state == "shortcut":
        log.warning(
            "%s: reference state 'shortcut': the sweep deforms the loaded reference "
            "scan taken as stress-free",
            work,
        )
    flipped = len(model.flipped_elements)
    if flipped:  # review BP, P3: a failed scenario at one of them says so too
        log.info(
            "%s: the stress-free reference holds %d element%s inverted at the clamped rim "
            "(calibration.json reference_recovery.inverted_elements): scenarios near the "
            "reference scan's own posture, where %s right side out again, may have no "
            "forward solution from it (a calibration with --reference-state prestress has "
            "none; another --mesh-size may have none)",
            work,
            flipped,
            "" if flipped == 1 else "s",
            "it is" if flipped == 1 else "they are",
        )
    plan = make_plan(
        opts.plan, c1_cal_pa=model.c1_pa, c1_axis=opts.c1_axis, holdout=opts.holdout, seed=opts.seed
    )
    if not model.scales_with_c1 and np.any(plan.c1_pa != model.c1_pa):
        raise PlanError(
            f"c1_axis (--c1) {opts.c1_axis}: {work} holds the back plate on tangential springs "
            "(model.effects, a diagnosis refit), whose stiffness does not scale with c1, so "
            "another c1 is not the calibrated one under scaled gravity; sweep without a c1 axis"
        )
    loads = plan.gravity_phantom * (model.c1_pa / plan.c1_pa)[:, None]
    cont = plan_continuation(loads, chunk_size=opts.chunk_size, max_angle_deg=opts.max_angle_deg)
    clean_stale(out.parent, (out.name,))  # staging folders of creations killed midway
    replacing = out.exists() and opts.overwrite and any(out.iterdir())
    old = None
    if replacing:
        if not _is_store(out):
            raise StoreError(
                f"out (--out) {out}: not a sweep store; overwrite (--overwrite) removes only stores"
            )
        old = SweepStore.open(out)
        old.lock()  # refuses a store that a live sweep is writing
        solved = int(np.sum(old.status() == SOLVED))
        if solved:  # review BT: a matching store too, which a plain run would resume
            log.warning("%s: --overwrite discards its %d solved scenario(s)", out, solved)
    store, backend = None, None

    def start_backend():
        return make_backend(
            opts.backend,
            workers=2 if opts.workers is None else opts.workers,
            dask=opts.dask,
            threads=opts.threads,
        )

    resumed = False
    try:
        if out.exists() and any(out.iterdir()) and not replacing:
            resumed = True
            store = SweepStore.open(out)
            store.check_matches(
                model, plan, chunk_size=opts.chunk_size, max_angle_deg=opts.max_angle_deg
            )
        else:
            # the backend first: one that cannot start (no scheduler at --dask) leaves the
            # old store and the file system as they were
            backend = start_backend()
            store = _create_new_store(out, model, plan, cont, opts, replacing=replacing)
            old = None  # replaced, lock and all
        store.lock()
        removed = store.clean_partial()
        if removed:
            log.info("%s: removed %d partial chunk files of an interrupted run", out, removed)
        lost = store.requeue_lost()
        if lost:
            log.warning(
                "%s: %d solved scenario(s) had result chunk files missing (a partial copy?): "
                "solving them again (scenario %d first)",
                *(out, len(lost), lost[0]),
            )
        status = store.status()
        pending = int(np.sum(status == PENDING)) + (
            int(np.sum(status == FAILED)) if opts.retry_failed else 0
        )
        before = store.attrs.get("status")
        if pending:
            # review BF: a resume that found lost chunks, killed, left "complete" with
            # scenarios pending
            store.mark_running()
        if progress is not None:
            progress({"start": True, "done": 0, "total": pending})
        info = {"backend": opts.backend, "workers": 0}
        run = {"solved": 0, "failed": 0, "retried": 0}
        if pending:
            if backend is None:
                try:
                    backend = start_backend()
                except BaseException:
                    # review BT: a --retry-failed resume whose backend could not start left
                    # a store with none pending marked running
                    if before is not None and not np.any(store.status() == PENDING):
                        store.set_status_attrs(before, store.attrs.get("summary", {}))
                    raise
            info = backend.describe()
            if resumed:  # review BK: once its backend runs (a failed start solves nothing)
                _record_resume(store, opts, model)
            run = run_scenarios(
                model, store, backend, retry_failed=opts.retry_failed, progress=progress
            )
        summary = _summary(store, info, run, time.perf_counter() - t0)
        store.set_status_attrs("complete" if summary["pending"] == 0 else "running", summary)
        return summary
    finally:
        if backend is not None:
            backend.close()
        if store is not None:
            store.unlock()
        if old is not None:
            old.unlock()


#: The distributions that set a sweep's numbers (the FE solve); a resume with other
#: versions of these is said (review BK: torch or dask are not among them)
_FE_PACKAGES = (
    *("phantom-calib", "numpy", "scipy", "scikit-fem", "tetgen", "meshio", "pypardiso"),
    "mkl",
)


def _other_edits(was: dict, now: dict) -> bool:
    """Whether two runs of one commit may run other code: edits not known to be the same.

    Both edited with one digest of their edits (``edits_sha256``) is the same code; a
    record without a digest (an older store's) is taken to differ.
    """
    if not (was.get("uncommitted_edits") or now.get("uncommitted_edits")):
        return False
    digest = was.get("edits_sha256")  # present only where the first run had edits
    return digest is None or digest != now.get("edits_sha256")


def _record_resume(store, opts: SweepOptions, model) -> None:
    """Add this run's provenance to the store's ``resumes``; warn where its code differs.

    The scenarios the store holds then come from runs of other commits, of uncommitted
    edits (not known to be the same: :func:`_other_edits`), or of other versions of the FE's
    libraries (:data:`_FE_PACKAGES`): equal to
    round-off where the solver is the same, but not one run's numbers. What the creating
    run did not record (an older store's) is not compared.
    """
    prov = _provenance(inputs=model.source, parameters=asdict(opts))
    first = store.attrs.get("provenance") or {}
    said = []
    was, now = first.get("source"), prov["source"]
    if was and now and was.get("commit") != now.get("commit"):
        said.append("another phantom-calib commit")
    elif was and now and _other_edits(was, now):
        said.append("uncommitted edits in a run (the code may differ)")
    elif bool(was) != bool(now) and "source" in first:
        said.append("phantom-calib from a checkout in one run and installed in the other")
    old = first.get("versions") or {}
    changed = [k for k in _FE_PACKAGES if k in old and old[k] != prov["versions"].get(k)]
    if changed:
        said.append("other versions of " + ", ".join(changed))
    if said:
        log.warning(
            "%s: resumed by a run that differs from the one that created the store (%s): "
            "its scenarios come from both (each run's record is in the store's `resumes`)",
            *(store.path, "; ".join(said)),
        )
    store.record_resume(prov)


def _create_new_store(out: Path, model, plan, cont, opts: SweepOptions, *, replacing: bool):
    """Create the store at ``out`` (replacing a store there), with any missing parents.

    Parent folders this call made are removed again if the creation fails.
    """
    import fem

    made = [p for p in (out.parent, *out.parent.parents) if not p.exists()]
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        disc = fem.discretize(model.tet_mesh(), fem.Clamped(), formulation=model.formulation)
        prov = _provenance(inputs=model.source, parameters=asdict(opts))
        return _create_store(out, model, plan, cont, disc.n_dofs, opts, prov, replacing=replacing)
    except BaseException:
        for p in made:  # deepest first
            try:
                p.rmdir()
            except OSError:
                break
        raise


def run_surrogate_train(
    sweep,
    out,
    *,
    kind: SurrogateKind = "ours",
    device: Device = "auto",
    seed: int = 0,
    iterations: int | None = None,
    progress=None,
) -> dict:
    """Train a surrogate on a sweep store and save it as TorchScript (``nn``).

    Parameters
    ----------
    sweep : path
        Sweep store.
    out : path
        Model file to write (``.pt``), atomically.
    kind : {"ours", "dissertation"}
        The reduced-basis kernel surrogate, or the dissertation's two MLPs.
    device : {"auto", "cpu", "cuda"}
    seed : int
    iterations : int, optional
        Training iterations of the dissertation MLPs (default 30 000).
    progress : callable, optional

    Returns
    -------
    dict
        The training report (also inside the model file).

    Raises
    ------
    ValueError
        An unknown ``kind`` or ``device``, ``cuda`` without a CUDA device,
        ``iterations`` below 1 or given for ``ours``, ``out`` not ``.pt``: checked before
        the store is read.
    IsADirectoryError
        ``out`` is a folder.
    nn.StoreFormatError
        ``sweep`` is not a readable sweep store, or has pending scenarios (a running or
        interrupted sweep: run it again to finish).
    """
    import nn

    from ..io import atomic_write, check_out_file

    if kind not in _KINDS:
        raise ValueError(f"unknown surrogate kind {kind!r}; choose ours or dissertation")
    nn.select_device(device)  # an unknown name, or cuda without a GPU, before any reading
    if iterations is not None and iterations < 1:
        raise ValueError(f"iterations (--iterations) must be >= 1, got {iterations}")
    if iterations is not None and kind == "ours":  # review AD: ignored without a word
        raise ValueError(
            "iterations (--iterations) are the dissertation MLPs' (kind 'dissertation'); "
            "ours has none"
        )
    if Path(out).suffix.lower() != ".pt":  # review AM: m.txt was written as a model
        raise ValueError(f"out (--out) {out}: a surrogate is a TorchScript file, name it .pt")
    check_out_file(out)
    data = nn.load_sweep(sweep, allow_pending=False)  # review AM: 4 of 12 read as all
    if kind == "ours":
        fit = nn.fit_reduced_kernel(data, device=device, progress=progress)
    else:
        kw = {} if iterations is None else {"iterations": iterations}
        fit = nn.fit_dissertation_mlps(data, device=device, seed=seed, progress=progress, **kw)
    sur = nn.Surrogate.from_fit(fit, data)
    # review BI: surrogate.json had no provenance (versions, commit, command, thread counts)
    sur.meta["provenance"] = _provenance(
        parameters={"kind": kind, "device": device, "seed": seed, "iterations": iterations}
    )
    atomic_write(out, lambda p: nn.save_surrogate(sur, p))
    return sur.report


def run_surrogate_predict(
    model_path,
    out,
    *,
    gravity,
    c1_pa: float | None = None,
    frame: PredictFrame = "phantom",
    extrapolate: bool = False,
) -> dict:
    """Predict the deformation for one gravity vector and write ``out`` (.vtu or .ply).

    Parameters
    ----------
    model_path : path
        A surrogate written by :func:`run_surrogate_train`.
    out : path
        ``.vtu`` (deformed tetrahedral mesh with ``displacement_mm``) or ``.ply``
        (deformed boundary surface with a per-vertex ``displacement_mm`` magnitude).
    gravity : array_like, shape (3,)
        Gravity acceleration vector in m/s^2 (its length is the magnitude; zero for no
        load), in the ``frame`` given.
    c1_pa : float, optional
        c1 of the prediction (default: the model's calibrated c1).
    frame : {"phantom", "ref"}
    extrapolate : bool
        Write a prediction not to be trusted at all (:class:`nn.FarExtrapolationWarning`:
        a load beyond 1.5 times the trained range, or nearer a scenario the sweep could
        not solve than any trained one); else nothing is written (review AM: ten times
        the trained load was written as 7e17 mm with exit status 0). Other
        extrapolations are written with their warning.

    Returns
    -------
    dict
        ``max_displacement_mm`` (over the file's vertices: every node of a ``.vtu``, the
        boundary's of a ``.ply``), ``tumour_mm``, ``nipple_mm``, ``out``.

    Raises
    ------
    ValueError
        ``out`` not ``.vtu`` or ``.ply``, or ``frame`` unknown (checked before the model
        is loaded); bad ``gravity`` or ``c1_pa``; a ``.vtu`` of a surface-only model; a
        far extrapolation without ``extrapolate``.
    IsADirectoryError
        ``out`` is a folder.
    nn.SurrogateFileError
        ``model_path`` is not a surrogate file.

    Warns
    -----
    nn.ExtrapolationWarning
        A query outside the trained range or directions (see
        :meth:`nn.Surrogate.predict`), written with its warning; a
        :class:`nn.FarExtrapolationWarning` only with ``extrapolate``.
    """
    import warnings

    import nn

    from ..io import check_out_file

    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in _PREDICT_SUFFIXES:
        raise ValueError(f"out (--out) {out}: write .vtu or .ply, got suffix {out.suffix!r}")
    if c1_pa is not None and not (np.isfinite(c1_pa) and c1_pa > 0):  # before the model's read
        raise ValueError(f"c1_pa (--c1) must be a positive stress in Pa, got {c1_pa!r}")
    if frame not in get_args(PredictFrame):
        raise ValueError(f"frame (--frame) must be 'phantom' or 'ref', got {frame!r}")
    check_out_file(out)
    sur = nn.load_surrogate(model_path)
    if suffix == ".vtu" and sur.surface_only:  # checked before predicting
        raise ValueError(f"{model_path}: this surrogate predicts surface nodes only; write a .ply")
    if suffix == ".ply" and not sur.boundary_known:
        raise ValueError(
            f"{model_path}: this surrogate predicts surface nodes only and its back plate "
            "is not clamped: its boundary is unknown"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", nn.ExtrapolationWarning)
        pred = sur.predict(np.asarray(gravity, float), c1_pa=c1_pa, frame=frame)
    for w in caught:
        if issubclass(w.category, nn.FarExtrapolationWarning) and not extrapolate:
            raise ValueError(f"{w.message}; nothing written (--extrapolate writes it anyway)")
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    mesh = sur.mesh
    if suffix == ".vtu":
        from fem import TetMesh
        from fem.io import write_mesh

        u = pred.nodes_mm[0]
        region = np.ones(len(mesh.tets), dtype=np.int64)
        deformed = TetMesh(mesh.nodes_mm + u, mesh.tets, region, {"bulk": 1})
        write_mesh(deformed, out, point_data={"displacement_mm": u})
    else:
        from imaging import SurfaceMesh, write_ply

        u_all = sur.boundary_displacement_mm(pred)
        keep = np.unique(mesh.boundary_faces)
        new_index = np.full(len(mesh.nodes_mm), -1)
        new_index[keep] = np.arange(len(keep))
        u = u_all[keep]
        surface = SurfaceMesh(
            mesh.nodes_mm[keep] + u,
            new_index[mesh.boundary_faces],
            back_plate=np.isin(keep, mesh.back_nodes),
        )
        write_ply(out, surface, vertex_scalars={"displacement_mm": np.linalg.norm(u, axis=1)})
    return {
        "max_displacement_mm": float(np.linalg.norm(u, axis=1).max()),
        "tumour_mm": None if pred.tumour_mm is None else pred.tumour_mm[0].tolist(),
        "nipple_mm": None if pred.nipple_mm is None else pred.nipple_mm[0].tolist(),
        "out": str(out),
    }
