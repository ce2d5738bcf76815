"""The sweep engine: solve scenarios on a backend, warm-started along the continuation.

One scenario is one task: the calibrated model (:class:`~calib.sweep.model.SweepModel`,
small and picklable), the gravity of the solve and the warm start (the parent's stored
solver vector, :mod:`calib.sweep.continuation`). Workers build the FE model once per
process (cached by the model's key) and return the result; only the driving process
writes the store, scenario by scenario (:class:`SweepStore.commit`). Pool workers run
one OpenMP/MKL thread each (set when they start); Dask's nanny starts its workers with
one such thread each by default (``distributed.nanny.pre-spawn-environ``); the serial
backend keeps the thread count of its process. A process solves one scenario at a time
(:data:`_SOLVE_LOCK`): a Dask worker of several task threads (``dask worker`` starts one
per core by default) would otherwise run two solves at once on the process's one FE
model cache and PARDISO instance, which failed them (review BT: 11 of 12 scenarios
recorded as failed solves on a worker of two threads).

PARDISO's results are bitwise reproducible for a fixed thread count and one sequence of
solves (:mod:`fem.linalg`; a worker reuses the analysis of the first matrix it solved, so
a scenario solved by another worker after others may differ in its last bits: review
BI); across thread counts they differ in the last bits (1e-16 mm on the quick twin).

Backends (:func:`make_backend`):

``serial``
    in this process, one scenario after the other;
``pool``
    a local process pool (``concurrent.futures``, spawned processes); a worker that
    dies breaks the pool, which is rebuilt, and the scenarios in flight are retried;
``dask``
    ``dask.distributed``: ``local`` starts a ``LocalCluster`` of ``workers`` processes
    (one thread each), an address ``tcp://HOST:PORT`` uses a running scheduler (an HPC
    cluster through dask-jobqueue). The scheduler retries the tasks of a lost worker
    (``distributed.scheduler.allowed-failures``); a task it gives up on is resubmitted
    here up to ``max_attempts`` times.

Scenario results do not depend on the backend: each task's inputs are fixed by the
plan (see :mod:`calib.sweep.continuation`).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future
from dataclasses import dataclass, field

import numpy as np

from .model import SweepModel

__all__ = [
    "Backend",
    "ScenarioResult",
    "ScenarioTask",
    "make_backend",
    "run_scenarios",
    "solve_scenario",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScenarioTask:
    """One solve: gravity (reference frame, unit), its magnitude and the warm start.

    Attributes
    ----------
    index : int
    gravity_ref : ndarray, shape (3,)
    g_m_s2 : float
        Gravity magnitude solved at the model's c1 (``g c1_model / c1``).
    x0 : ndarray or None
        Solver vector of the parent scenario, None for a cold start.
    attempt : int
    """

    index: int
    gravity_ref: np.ndarray
    g_m_s2: float
    x0: np.ndarray | None = None
    attempt: int = 1


@dataclass(frozen=True)
class ScenarioResult:
    """The outcome of one :class:`ScenarioTask`.

    Attributes
    ----------
    index : int
    ok : bool
    displacement_mm : ndarray, shape (n_nodes, 3) or None
    state : ndarray, shape (n_dofs,) or None
    tumour_mm, nipple_mm : ndarray, shape (3,) or None
        Displacements of the tumour-centre material point and the nipple vertex.
    stats : dict
        ``newton_iterations``, ``load_steps``, ``cutbacks``, ``factorizations``,
        ``wall_s``, ``warm_start``, ``attempts``, ``final_residual``, ``cpu_s``.
    message : str
        Why the scenario failed (empty when ``ok``).
    worker : str
        ``host:pid`` of the process that solved it.
    """

    index: int
    ok: bool
    displacement_mm: np.ndarray | None = None
    state: np.ndarray | None = None
    tumour_mm: np.ndarray | None = None
    nipple_mm: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    message: str = ""
    worker: str = ""


# -- worker side ---------------------------------------------------------------------------
_CACHE: dict = {}  # model key -> (fem.Model, Discretization, MaterialPoint or None, Prestress)
#: Held by a solve: the model cache and fem's PARDISO instances are per process, not per
#: thread, so the threads of one worker process take turns.
_SOLVE_LOCK = threading.Lock()


def _prepared(model: SweepModel, key: str):
    if key not in _CACHE:
        import fem
        from fem.probe import MaterialPoint

        _CACHE.clear()  # one model per worker at a time
        fm = model.fem_model()
        disc = fem.discretize(fm.mesh, fm.support, formulation=model.formulation)
        tumour = None
        if model.tumour_stress_free_mm is not None:
            tumour = MaterialPoint.locate(disc, model.tumour_stress_free_mm)
        _CACHE[key] = (fm, disc, tumour, model.prestress(fm, disc))
    return _CACHE[key]


def _flipped_note(model: SweepModel, exc: Exception) -> str:
    """What a failure at an element inverted in the stress-free mesh means ("" otherwise).

    fem's message says the load may be too large or the support leave the body free; at
    one of :attr:`SweepModel.flipped_elements` it is the recovered reference instead
    (review BP, P3).
    """
    element = getattr(exc, "element", None)
    flipped = model.flipped_elements if element is not None else ()
    if element is None or element not in flipped:
        return ""
    return (
        f" (element {element} is one of the {len(flipped)} the stress-free reference holds "
        "inverted at the clamped rim, calibration.json's reference_recovery."
        "inverted_elements: near the reference scan's own posture they may have to turn "
        "right side out, which no forward solve from the stress-free mesh reaches; a "
        "calibration with --reference-state prestress has none, another --mesh-size may "
        "have none)"
    )


def solve_scenario(model: SweepModel, key: str, task: ScenarioTask):
    """Solve one scenario (runs on a worker; never raises for a failed solve).

    Parameters
    ----------
    model : SweepModel
    key : str
        ``model.key`` (computed once by the driver).
    task : ScenarioTask

    Returns
    -------
    ScenarioResult
        Solved, or failed with its message; threads of one process take turns
        (:data:`_SOLVE_LOCK`).
    """
    with _SOLVE_LOCK:  # one solve per process at a time (module docstring)
        return _solve_scenario(model, key, task)


def _solve_scenario(model: SweepModel, key: str, task: ScenarioTask) -> ScenarioResult:
    import fem

    t0, c0 = time.perf_counter(), time.process_time()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        fm, disc, tumour, ps = _prepared(model, key)
        # ps: the prestressed loaded mesh (see calib.sweep.model), else None
        out = fem.solve_posture(
            fm, gravity=task.gravity_ref, g_m_s2=task.g_m_s2, disc=disc, prestress=ps, x0=task.x0
        )
        if out.retried is not None:
            log.info("scenario %d: %s; retried with small load steps", task.index, out.retried)
        sol, newton = out.solution, out.failed_newton
    except Exception as exc:  # a failed scenario is recorded, not fatal
        return ScenarioResult(
            task.index,
            False,
            message=f"{type(exc).__name__}: {exc}{_flipped_note(model, exc)}",
            worker=worker,
            stats={
                "wall_s": time.perf_counter() - t0,
                "attempts": task.attempt,
                "warm_start": float(task.x0 is not None),
            },
        )
    stats = {
        "newton_iterations": sol.newton_iterations + newton,
        "load_steps": sol.load_steps,
        "cutbacks": sol.cutbacks,
        "factorizations": sol.factorizations,
        "wall_s": time.perf_counter() - t0,
        "warm_start": float(task.x0 is not None),
        "attempts": task.attempt,
        "final_residual": sol.residual_history[-1] if sol.residual_history else 0.0,
        "cpu_s": time.process_time() - c0,
    }
    u = sol.displacement_mm
    return ScenarioResult(
        index=task.index,
        ok=True,
        displacement_mm=u,
        state=sol.state,
        tumour_mm=np.full(3, np.nan) if tumour is None else tumour.displacement_mm(sol.state),
        nipple_mm=u[model.nipple_node].copy(),
        stats=stats,
        worker=worker,
    )


def _init_worker(threads: int) -> None:
    """Pool initializer: the worker's thread count, once, before its first solve.

    Environment variables for libraries loaded later (MKL, with the first PARDISO
    solve) and threadpoolctl for those already loaded (OpenBLAS). Never changed again:
    a cached PARDISO solver set up for reproducibility at one thread count can crash
    when MKL's thread count changes between its factorizations (seen with MKL 2026.2).
    """
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    from threadpoolctl import threadpool_limits  # a dependency

    threadpool_limits(limits=threads)  # for the life of the worker process


# -- backends ------------------------------------------------------------------------------
class WorkerLost(RuntimeError):
    """The process running a task died (the task is retried)."""


class Backend:
    """A place to run tasks: ``submit`` returns a future, ``wait`` the finished ones."""

    name = "serial"
    slots = 1

    def submit(self, fn: Callable, *args) -> Future:
        """Run ``fn(*args)`` (here: at once) and return its future."""
        fut: Future = Future()
        try:
            fut.set_result(fn(*args))
        except Exception as exc:  # delivered through the future
            fut.set_exception(exc)
        return fut

    def wait(self, futures: list) -> list:
        """The finished futures among ``futures`` (blocks until at least one is)."""
        return [f for f in futures if f.done()]

    def result(self, fut):
        """The future's result; :class:`WorkerLost` when its worker died."""
        return fut.result()

    def recover(self) -> bool:
        """Make the backend usable after a lost worker; True when every task in flight is lost."""
        return False

    def describe(self) -> dict:
        """Backend name and worker count (recorded in the store's summary)."""
        return {"backend": self.name, "workers": self.slots}

    def close(self) -> None:
        """Release processes and connections."""


class PoolBackend(Backend):
    """A local process pool (spawned processes, one thread each)."""

    name = "pool"

    def __init__(self, workers: int, threads: int = 1):
        self.slots, self.threads = int(workers), int(threads)
        self._pool = None
        self._start()

    def _start(self) -> None:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        self._pool = ProcessPoolExecutor(
            max_workers=self.slots,
            mp_context=mp.get_context("spawn"),
            initializer=_init_worker,
            initargs=(self.threads,),
        )

    def submit(self, fn, *args) -> Future:
        from concurrent.futures.process import BrokenProcessPool

        try:
            return self._pool.submit(fn, *args)
        except BrokenProcessPool as exc:  # a worker died since the last wait
            fut: Future = Future()
            fut.set_exception(exc)
            return fut

    def wait(self, futures: list) -> list:
        from concurrent.futures import wait

        done, _ = wait(futures, return_when=FIRST_COMPLETED)
        return list(done)

    def result(self, fut):
        from concurrent.futures.process import BrokenProcessPool

        try:
            return fut.result()
        except BrokenProcessPool as exc:
            raise WorkerLost(str(exc)) from exc

    def recover(self) -> bool:
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._start()
        return True

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskBackend(Backend):
    """dask.distributed: a LocalCluster started here, or a running scheduler's address."""

    name = "dask"

    def __init__(self, address: str, workers: int, threads: int = 1):
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:
            raise RuntimeError(
                "the dask backend needs dask.distributed: pip install 'phantom-calib[sweep]'"
            ) from exc
        self.threads, self.cluster = int(threads), None
        if address == "local":
            self.cluster = LocalCluster(
                n_workers=int(workers),
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                # the scheduler's HTTP server (health routes) starts even without a dashboard and
                # would ask for port 8787 first; a free port instead
                scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                silence_logs=logging.ERROR,
            )
            self.client = Client(self.cluster)
        else:
            try:
                self.client = Client(address, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise RuntimeError(f"cannot reach the Dask scheduler at {address}: {exc}") from exc
        self.address = address
        n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        self.slots = max(n, 1)

    def submit(self, fn, *args):
        return self.client.submit(fn, *args, pure=False)

    def wait(self, futures: list) -> list:
        from distributed import wait

        done, _ = wait(futures, return_when="FIRST_COMPLETED")
        return list(done)

    def result(self, fut):
        from distributed import KilledWorker

        try:
            return fut.result()
        except KilledWorker as exc:
            raise WorkerLost(str(exc)) from exc

    def describe(self) -> dict:
        n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        return {"backend": "dask", "workers": n, "scheduler": self.address}

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def make_backend(kind: str, *, workers: int = 2, dask: str | None = None, threads: int = 1):
    """A backend: ``serial``, ``pool`` (``workers`` processes) or ``dask`` (``dask`` address).

    Parameters
    ----------
    kind : {"serial", "pool", "dask"}
    workers : int
        Processes of the pool or of a local Dask cluster.
    dask : str, optional
        ``local`` or ``tcp://HOST:PORT`` (for ``kind="dask"``).
    threads : int
        Threads per solve.

    Returns
    -------
    Backend
    """
    if workers < 1:
        raise ValueError(f"workers (--workers) must be >= 1, got {workers}")
    if kind == "serial":
        return Backend()
    if kind == "pool":
        return PoolBackend(workers, threads)
    if kind == "dask":
        return DaskBackend(dask or "local", workers, threads)
    raise ValueError(f"unknown backend {kind!r}; choose serial, pool or dask")


# -- driver --------------------------------------------------------------------------------
@dataclass
class _Progress:
    total: int
    done: int = 0
    solved: int = 0
    failed: int = 0
    retried: int = 0
    newton: list = field(default_factory=list)


def run_scenarios(
    model: SweepModel,
    store,
    backend: Backend,
    *,
    retry_failed: bool = False,
    max_attempts: int = 3,
    progress: Callable[[dict], None] | None = None,
) -> dict:
    """Solve every pending scenario of ``store`` on ``backend``, committing each one.

    A scenario is submitted when its parent (see :mod:`calib.sweep.continuation`) is
    committed; its warm start is the parent's stored solver vector (a cold start when the
    parent failed). At most ``2 x backend.slots`` tasks are in flight, in tour order.

    Parameters
    ----------
    model : SweepModel
    store : SweepStore
    backend : Backend
    retry_failed : bool
        Solve scenarios recorded as failed again.
    max_attempts : int
        Tries of a scenario whose worker died.
    progress : callable, optional
        Called after every committed scenario with a dict (``done``, ``total``,
        ``index``, ``ok``, ``newton_iterations``, ``wall_s``, ``worker``).

    Returns
    -------
    dict
        ``solved``, ``failed``, ``retried`` (tasks resubmitted after a lost worker) and
        ``newton`` (iterations of each solve of this run).
    """
    from .store import FAILED, PENDING, SOLVED

    key = model.key
    status = store.status()
    parent = store.scenario_array("parent")
    order = store.scenario_array("order")
    g_ref = store.scenario_array("gravity_ref")
    g_solved = store.scenario_array("g_m_s2_solved")
    todo = [int(i) for i in order if status[i] == PENDING or (retry_failed and status[i] == FAILED)]
    for i in todo:
        status[i] = PENDING
    prog = _Progress(total=len(todo))
    attempts = dict.fromkeys(todo, 0)
    in_flight: dict = {}  # future -> scenario
    queue = list(todo)
    rank = {int(i): k for k, i in enumerate(order)}
    streak, committed_since_loss = 0, False

    def ready(i: int) -> bool:
        p = parent[i]
        return p < 0 or status[p] != PENDING

    def submit(i: int) -> None:
        p = parent[i]
        x0 = store.state(p) if p >= 0 and status[p] == SOLVED else None
        attempts[i] += 1
        task = ScenarioTask(i, g_ref[i], float(g_solved[i]), x0, attempts[i])
        in_flight[backend.submit(solve_scenario, model, key, task)] = i

    while queue or in_flight:
        for i in [i for i in queue if ready(i)][: max(0, 2 * backend.slots - len(in_flight))]:
            queue.remove(i)
            submit(i)
        if not in_flight:
            raise RuntimeError("sweep scheduling stalled: scenarios wait on unsolved parents")
        lost = []
        for fut in backend.wait(list(in_flight)):
            i = in_flight.pop(fut)
            try:
                res = backend.result(fut)
            except WorkerLost as exc:
                log.warning("scenario %d: worker lost (%s)", i, exc)
                lost.append(i)
                continue
            _commit(store, status, prog, res, progress)
            committed_since_loss = True
        if lost:
            streak = 1 if committed_since_loss else streak + 1  # rounds lost in a row
            committed_since_loss = False
            if streak >= max_attempts:
                raise RuntimeError(
                    f"{backend.name} workers died {streak} times in a row without solving a "
                    "scenario (out of memory? a script without `if __name__ == '__main__':` "
                    "starting spawned workers?); the solved scenarios are kept, run again "
                    "to resume"
                )
            if backend.recover():  # every task in flight went down with the pool
                lost += list(in_flight.values())
                in_flight.clear()
            for i in sorted(set(lost), key=lambda j: rank[j]):
                if attempts[i] >= max_attempts:
                    res = ScenarioResult(
                        i,
                        False,
                        message=f"worker lost {attempts[i]} times",
                        stats={"attempts": attempts[i]},
                    )
                    _commit(store, status, prog, res, progress)
                else:
                    prog.retried += 1
                    queue.insert(0, i)
    return {
        "solved": prog.solved,
        "failed": prog.failed,
        "retried": prog.retried,
        "newton": prog.newton,
    }


def _commit(store, status, prog: _Progress, res: ScenarioResult, progress) -> None:
    from .store import FAILED, SOLVED

    store.commit(res.index, res)
    status[res.index] = SOLVED if res.ok else FAILED
    prog.done += 1
    if res.ok:
        prog.solved += 1
        prog.newton.append(int(res.stats["newton_iterations"]))
    else:
        prog.failed += 1
        log.warning("scenario %d failed: %s", res.index, res.message)
    if progress is not None:
        progress(
            {
                "done": prog.done,
                "total": prog.total,
                "index": res.index,
                "ok": res.ok,
                "newton_iterations": res.stats.get("newton_iterations"),
                "wall_s": res.stats.get("wall_s"),
                "worker": res.worker,
                "message": res.message,
            }
        )
