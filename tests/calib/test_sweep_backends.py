"""Backends give the same numbers; killed workers and a killed sweep lose nothing.

The reference is a serial sweep. Each scenario's inputs (gravity, warm start = the
parent's stored solver vector) are fixed by the plan, and the FE solve is a
deterministic function of them (PARDISO with a fixed ordering and conditional numerical
reproducibility at one thread, fem.linalg), so every backend, any interruption and any
retry must give the same bits; the 1e-9 mm asked by the issue is checked.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nn"))
from sweep_helpers import make_box_work

from calib.workflows.sweep import SweepOptions, run_sweep

PLAN = {"plan": "sphere:12", "c1_axis": "400:700:2", "chunk_size": 4}
TOL_MM = 1e-9


def _disp(store) -> np.ndarray:
    import zarr

    g = zarr.open_group(store, mode="r")
    assert np.all(np.asarray(g["results/status"][:]) == 1)
    return np.asarray(g["results/displacement_mm"][:])


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return make_box_work(tmp_path_factory.mktemp("backends") / "work")


@pytest.fixture(scope="module")
def serial(work, tmp_path_factory):
    out = tmp_path_factory.mktemp("backends") / "serial"
    run_sweep(work, out, SweepOptions(backend="serial", **PLAN))
    return _disp(out)


def _spawned_children() -> list:
    """Worker processes started by multiprocessing's spawn (pool or Dask nanny) here."""
    import psutil

    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            if any("spawn_main" in part for part in p.cmdline()):
                out.append(p)
        except psutil.Error:
            pass
    return out


def _killer(n_before_kill: int):
    """A progress callback that SIGKILLs one worker after ``n`` committed scenarios."""
    state = {"n": 0, "killed": None}

    def progress(ev):
        if ev.get("start"):
            return
        state["n"] += 1
        if state["n"] == n_before_kill and state["killed"] is None:
            workers = _spawned_children()
            assert workers, "no worker process found to kill"
            state["killed"] = workers[0].pid
            os.kill(workers[0].pid, signal.SIGKILL)

    return progress, state


def test_pool_with_a_killed_worker_matches_serial(work, serial, tmp_path):
    progress, state = _killer(3)
    s = run_sweep(
        work, tmp_path / "pool", SweepOptions(backend="pool", workers=2, **PLAN), progress=progress
    )
    assert state["killed"] is not None
    # the pool broke; the scenarios in flight were retried on a new pool
    assert s["this_run"]["retried_after_lost_worker"] >= 1
    assert s["solved"] == 24 and s["failed"] == 0
    assert np.abs(_disp(tmp_path / "pool") - serial).max() <= TOL_MM


def _local_cluster(*, n_workers: int, threads_per_worker: int):
    """A running LocalCluster of worker processes, to be reached by its address."""
    import logging

    distributed = pytest.importorskip("distributed")
    return distributed.LocalCluster(
        n_workers=n_workers,
        threads_per_worker=threads_per_worker,
        processes=True,
        dashboard_address=None,
        # the scheduler's HTTP server (health routes) starts even without a dashboard and
        # would ask for port 8787 first; a free port instead
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.ERROR,
    )


def test_dask_cluster_at_an_address_with_a_killed_worker_matches_serial(work, serial, tmp_path):
    # a running two-worker LocalCluster reached by its address (--dask tcp://HOST:PORT,
    # the HPC path); `--dask local` starts the same cluster itself (benchmarks/bench_sweep)
    with _local_cluster(n_workers=2, threads_per_worker=1) as cluster:
        progress, state = _killer(3)
        opts = SweepOptions(backend="dask", dask=cluster.scheduler_address, **PLAN)
        s = run_sweep(work, tmp_path / "dask", opts, progress=progress)
        assert state["killed"] is not None
        assert s["this_run"]["scheduler"].startswith("tcp://")
        # the scheduler reran the lost worker's task (its nanny restarts it); the cluster
        # is not ours to close
        assert s["solved"] == 24 and s["failed"] == 0
        assert cluster.scheduler.status.name == "running"
    assert np.abs(_disp(tmp_path / "dask") - serial).max() <= TOL_MM


def test_a_dask_worker_of_two_threads_matches_serial(work, serial, tmp_path):
    # review BT: `dask worker ADDR` starts a thread per core; two solves at once in one
    # process shared its model cache and PARDISO instance and failed (11 of 12 recorded
    # as failed solves); the worker's threads now take turns
    with _local_cluster(n_workers=1, threads_per_worker=2) as cluster:
        opts = SweepOptions(backend="dask", dask=cluster.scheduler_address, **PLAN)
        s = run_sweep(work, tmp_path / "dask2", opts)
    assert s["solved"] == 24 and s["failed"] == 0
    assert np.abs(_disp(tmp_path / "dask2") - serial).max() <= TOL_MM


def test_kill_9_of_a_running_sweep_then_resume(work, serial, tmp_path):
    import zarr

    out = tmp_path / "killed"
    args = [
        "sweep",
        str(work),
        "--out",
        str(out),
        "--plan",
        PLAN["plan"],
        "--c1",
        PLAN["c1_axis"],
        "--chunk-size",
        str(PLAN["chunk_size"]),
        "--serial",
    ]
    env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    log = tmp_path / "stderr.txt"
    with open(log, "wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "calib", *args],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=err,
            start_new_session=True,
        )
    status = out / "results" / "status" / "c"

    def committed() -> int:
        # zarr writes a chunk to "<i>.<uuid>.partial" and renames it: only the digit
        # names are status chunks on disk
        return sum(p.name.isdigit() for p in status.iterdir()) if status.is_dir() else 0

    t0 = time.monotonic()
    try:
        while committed() < 4:
            assert proc.poll() is None, log.read_text()
            # a hang guard, not a timing: the sweep solves its first 4 scenarios in a few
            # seconds (make_box_work's block); 120 s only stops a loop that would wait forever
            assert time.monotonic() - t0 < 120, "the sweep did not start solving in 2 min"
            time.sleep(0.005)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the sweep we started, with any children
        proc.wait()
    done = np.asarray(zarr.open_group(out, mode="r")["results/status"][:])
    assert 4 <= np.sum(done == 1) < len(done), "kill came too late to test a resume"
    assert (out / ".lock").exists()  # left by the killed run; its process is dead
    # resume in this process: the scenarios solved before the kill are kept, not redone
    s = run_sweep(work, out, SweepOptions(backend="serial", **PLAN))
    assert s["solved"] == len(done) and s["this_run"]["solved"] == len(done) - np.sum(done == 1)
    assert not list(out.rglob("*.partial")) and not (out / ".lock").exists()
    # and the numbers of an uninterrupted sweep
    assert np.abs(_disp(out) - serial).max() <= TOL_MM


def test_a_failed_scenario_retried_matches_serial_and_leaves_no_failure(
    work, serial, tmp_path, monkeypatch
):
    # review AD: after a successful --retry-failed the `failures` attribute still listed
    # the scenario. Its children were solved cold meanwhile: within TOL_MM of the serial
    # sweep's warm starts (review AD measured 1.4e-12 mm)
    import zarr

    import fem

    real, calls = fem.solve_posture, {"n": 0}

    def first_fails(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 1:
            raise fem.ConvergenceError("simulated failure")
        return real(*args, **kw)

    out = tmp_path / "retry"
    monkeypatch.setattr(fem, "solve_posture", first_fails)
    summary = run_sweep(work, out, SweepOptions(backend="serial", **PLAN))
    assert (summary["solved"], summary["failed"]) == (23, 1)
    assert len(zarr.open_group(out, mode="r").attrs["failures"]) == 1
    monkeypatch.setattr(fem, "solve_posture", real)
    summary = run_sweep(work, out, SweepOptions(backend="serial", retry_failed=True, **PLAN))
    assert (summary["solved"], summary["failed"]) == (24, 0)
    assert zarr.open_group(out, mode="r").attrs["failures"] == {}
    np.testing.assert_allclose(_disp(out), serial, rtol=0, atol=TOL_MM)
