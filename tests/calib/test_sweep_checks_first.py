"""``phantom-calib sweep``: a refused option reads no calibration and leaves nothing on disk.

The README promises that options are checked before any work; a ``--workers 0`` or a
malformed ``--dask`` used to fail only after the store had been created (audit item 1).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nn"))
from sweep_helpers import make_box_work

import calib.sweep
import calib.sweep.engine
from calib.cli import app
from calib.workflows import sweep as wsweep
from calib.workflows.sweep import SweepOptions, run_sweep


@pytest.fixture
def no_reading(monkeypatch):
    """Fail the test if the calibration is read (the first work of a sweep)."""

    def refuse(work):
        raise AssertionError(f"the calibration of {work} was read before the options were checked")

    monkeypatch.setattr(calib.sweep, "load_sweep_model", refuse)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"workers": 0}, r"^workers \(--workers\) must be an integer >= 1, got 0"),
        ({"chunk_size": 0}, r"^chunk_size \(--chunk-size\) must be an integer >= 1"),
        ({"threads": 0}, "threads must be an integer >= 1"),
        ({"backend": "mpi"}, "unknown backend 'mpi'"),
        (
            {"backend": "dask", "dask": "locall"},
            r"^dask \(--dask\) must be 'local' or .*tcp://HOST:PORT",
        ),
        ({"backend": "dask", "dask": "tcp//10.0.0.5:8786"}, r"^dask \(--dask\) must be"),
        ({"backend": "dask", "dask": "tcp://10.0.0.5"}, r"^dask \(--dask\) must be"),
        ({"backend": "dask", "dask": "tcp://10.0.0.5:99999"}, r"^dask \(--dask\) must be"),
        # review AW: a scheduler's address with another backend, or with --workers (its
        # workers are its own), was ignored without a word
        (
            {"backend": "serial", "dask": "local"},
            r"dask \(--dask\) goes with backend 'dask', not 'serial'",
        ),
        (
            {"backend": "pool", "dask": "tcp://10.0.0.5:8786"},
            r"dask \(--dask\) goes with backend 'dask'",
        ),
        # its form first (review AY: "LOCAL" was called a scheduler, and "" given on the
        # command line, which picks the pool, was said to need backend dask)
        (
            {"backend": "dask", "dask": "LOCAL", "workers": 3},
            r"^dask \(--dask\) must be 'local' or",
        ),
        ({"backend": "pool", "dask": ""}, r"^dask \(--dask\) must be 'local' or .*got ''"),
        (
            {"backend": "dask", "dask": "tcp://10.0.0.5:8786", "workers": 4},
            r"the scheduler at tcp://10.0.0.5:8786 has its own workers: drop workers \(--workers\)",
        ),
        # review BD: the plan, c1 axis and hold-out were checked after the calibration
        # was read (its c1 only fills a plan without a c1 axis)
        ({"plan": "sphere:0"}, r"^plan \(--plan\) sphere:N needs a positive integer N"),
        ({"plan": "grid"}, r"unknown plan \(--plan\) 'grid'"),
        ({"holdout": 0.3}, r"^plan \(--plan\) dissertation has its own validation directions"),
        ({"plan": "sphere:10", "holdout": 1.0}, r"^holdout \(--holdout\) must lie in \[0, 1\)"),
        ({"plan": "sphere:10", "holdout": 0.04}, "holds 0 out"),
        ({"c1_axis": "300:600"}, r"^c1_axis \(--c1\) must be LO:HI:N"),
        ({"c1_axis": "600:300:3"}, "need 0 < LO <= HI"),
        # review BK: NaN was taken, and its store never matched itself on resume
        ({"max_angle_deg": float("nan")}, r"max_angle_deg must be an angle in \[0, 180\]"),
        ({"max_angle_deg": -1.0}, "got -1.0"),
    ],
)
def test_bad_options_are_refused_when_built(kw, match):
    with pytest.raises(ValueError, match=match):
        SweepOptions(**kw)


@pytest.mark.parametrize(
    "address", ["local", "tcp://10.0.0.5:8786", "tls://sched.hpc:8786", "tcp://[::1]:8786"]
)
def test_good_dask_addresses_are_accepted(address):
    assert SweepOptions(backend="dask", dask=address).dask == address


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--workers", "0"], "workers (--workers) must be an integer >= 1, got 0"),
        (["--dask", "tcp//10.0.0.5:8786"], "dask (--dask) must be 'local' or"),
        (["--chunk-size", "0"], "chunk_size (--chunk-size) must be"),
        (["--plan", "sphere:x"], "plan (--plan) sphere:N needs a positive integer N"),
        (["--c1", "0:300:3"], "need 0 < LO <= HI"),
    ],
)
def test_cli_refuses_before_reading_or_writing(tmp_path, no_reading, args, match):
    out = tmp_path / "sub" / "SWEEP"
    res = CliRunner().invoke(app, ["sweep", str(tmp_path / "work"), "--out", str(out), *args])
    assert res.exit_code == 2, res.output
    assert match in res.output
    assert not out.exists() and not out.parent.exists()


def test_a_refused_work_folder_s_error_comes_alone(tmp_path, capfd):
    # review AM: the progress bar, started before the work folder was read, printed a blank
    # line before the error (rich writes to the process's own stdout, not the runner's)
    out = tmp_path / "SWEEP"
    res = CliRunner().invoke(app, ["sweep", str(tmp_path / "nowhere"), "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert res.output.startswith("error:") and "no such work folder" in res.output
    assert capfd.readouterr().out == ""
    assert not out.exists()


def test_dask_backend_without_distributed_is_refused_first(tmp_path, no_reading, monkeypatch):
    monkeypatch.setattr(wsweep, "_has_distributed", lambda: False)
    out = tmp_path / "SWEEP"
    with pytest.raises(RuntimeError, match=r"needs dask\.distributed"):
        run_sweep(tmp_path / "work", out, SweepOptions(backend="dask", dask="local"))
    assert not out.exists()


def test_a_backend_that_cannot_start_leaves_no_store(tmp_path, monkeypatch):
    # the address's form is checked first; whether a scheduler answers there is known only
    # when it is reached, after the store exists: the store this run created goes again
    work = make_box_work(tmp_path / "work")

    def unreachable(*args, **kw):
        raise RuntimeError("cannot reach the Dask scheduler at tcp://10.0.0.5:8786")

    monkeypatch.setattr(calib.sweep.engine, "make_backend", unreachable)
    opts = SweepOptions(plan="sphere:6", backend="dask", dask="tcp://10.0.0.5:8786")
    with pytest.raises(RuntimeError, match="cannot reach"):
        run_sweep(work, tmp_path / "s", opts)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]
    (tmp_path / "empty").mkdir()  # an empty folder given as --out stays an empty folder
    with pytest.raises(RuntimeError, match="cannot reach"):
        run_sweep(work, tmp_path / "empty", opts)
    assert not any((tmp_path / "empty").iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "work"]


def test_a_resume_whose_backend_cannot_start_keeps_the_store_s_status(tmp_path, monkeypatch):
    # review BT: `--retry-failed` on a complete store with a failed scenario marked it
    # running before its backend failed to start, and left it so, none pending
    import zarr

    work = make_box_work(tmp_path / "work")
    store = tmp_path / "s"
    run_sweep(work, store, SweepOptions(plan="sphere:6"))
    zarr.open_group(store, mode="r+")["results/status"][0] = 2  # as a failed solve leaves it
    assert zarr.open_group(store, mode="r").attrs["status"] == "complete"

    def unreachable(*args, **kw):
        raise RuntimeError("cannot reach the Dask scheduler at tcp://10.0.0.5:8786")

    monkeypatch.setattr(calib.sweep.engine, "make_backend", unreachable)
    opts = SweepOptions(plan="sphere:6", backend="dask", dask="tcp://10.0.0.5:8786")
    with pytest.raises(RuntimeError, match="cannot reach"):
        run_sweep(work, store, replace(opts, retry_failed=True))
    assert zarr.open_group(store, mode="r").attrs["status"] == "complete"


def _tree(path: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()
    }


def test_overwrite_keeps_the_old_store_when_the_backend_cannot_start(tmp_path, monkeypatch, caplog):
    # the old store used to be removed before the scheduler was reached: an unreachable
    # --dask with --overwrite lost it
    work = make_box_work(tmp_path / "work")
    store = tmp_path / "s"
    run_sweep(work, store, SweepOptions(plan="sphere:6"))
    before = _tree(store)

    def unreachable(*args, **kw):
        raise RuntimeError("cannot reach the Dask scheduler at tcp://10.0.0.5:8786")

    monkeypatch.setattr(calib.sweep.engine, "make_backend", unreachable)
    opts = SweepOptions(plan="sphere:8", backend="dask", dask="tcp://10.0.0.5:8786", overwrite=True)
    with pytest.raises(RuntimeError, match="cannot reach"):
        run_sweep(work, store, opts)
    assert _tree(store) == before  # the old store, lock released, nothing beside it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s", "work"]
    monkeypatch.undo()
    summary = run_sweep(work, store, SweepOptions(plan="sphere:8", overwrite=True))
    assert summary["pending"] == 0 and summary["solved"] == 8
    # review BT: a store of this very plan is replaced too, and says what it discards
    with caplog.at_level("WARNING", logger="calib.workflows.sweep"):
        run_sweep(work, store, SweepOptions(plan="sphere:8", overwrite=True))
    assert "--overwrite discards its 8 solved scenario(s)" in caplog.text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s", "work"]


def test_parent_folders_made_for_out_go_when_the_creation_fails(tmp_path, monkeypatch):
    work = make_box_work(tmp_path / "work")

    from calib.sweep.store import SweepStore

    real_create = SweepStore.create

    def broken(path, *args, **kw):
        real_create(path, *args, **kw)  # a store half written, then the disk is full
        raise OSError("disk full")

    monkeypatch.setattr(SweepStore, "create", staticmethod(broken))
    with pytest.raises(OSError, match="disk full"):
        run_sweep(work, tmp_path / "a" / "b" / "SWEEP", SweepOptions(plan="sphere:6"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]


def test_a_store_made_at_out_by_another_sweep_meanwhile_is_not_replaced(tmp_path, monkeypatch):
    # review BT: two sweeps started together on one --out (a job array); the second found
    # no store, and while it created its own the first made and locked one there; the
    # second then replaced it without --overwrite, and the first wrote into its store
    from calib.sweep.store import StoreError, SweepStore

    work = make_box_work(tmp_path / "work")
    out = tmp_path / "SWEEP"
    real_create = SweepStore.create

    def raced(path, *args, **kw):
        real_create(path, *args, **kw)
        out.mkdir(exist_ok=True)  # the other sweep's store, just before ours moves in
        (out / "theirs").write_text("a store being written")

    monkeypatch.setattr(SweepStore, "create", staticmethod(raced))
    with pytest.raises(StoreError, match="a store appeared there while this one was being"):
        run_sweep(work, out, SweepOptions(plan="sphere:6"))
    assert sorted(p.name for p in out.iterdir()) == ["theirs"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["SWEEP", "work"]  # no staging left


@pytest.mark.parametrize("c1", [-5.0, float("nan"), "abc"])
def test_a_calibration_without_a_physical_c1_is_refused_before_sweeping(tmp_path, c1):
    # review AC: c1 -5 or NaN swept every scenario to a failure and exited 0
    import json

    from calib.sweep import load_sweep_model

    work = make_box_work(tmp_path / "work")
    path = work / "calibration.json"
    doc = json.loads(path.read_text())
    doc["c1_pa"] = c1
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"calibration.json: `c1_pa` must be a positive number"):
        load_sweep_model(work)


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda m: m.update(tumour_stress_free_mm=[500.0, 500.0, 500.0]), "lies outside the model"),
        (lambda m: m.update(tumour_stress_free_mm=[1.0, 2.0]), "is not a finite point"),
        (lambda m: m.update(nipple_node=10**6), "nipple_node 1000000 is not a node"),
        (lambda m: m.update(nipple_node=-1), "nipple_node -1 is not a node"),
        # review AC: swept every scenario to a failure; now check_record's, one place
        (lambda m: m.update(nu=0.7), r"`model.nu` must be a number in \(0, 0.5\)"),
        (lambda m: m.update(g_m_s2=float("nan")), "`model.g_m_s2` must be a positive number"),
        (
            lambda m: m.update(R_ref_from_phantom=[[-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]),
            r"`model.R_ref_from_phantom` must be a 3x3 rotation \(orthonormal, det \+1\)",
        ),
    ],
)
def test_a_model_block_that_cannot_be_swept_is_refused_before_sweeping(tmp_path, edit, says):
    # review AD: a tumour outside the mesh failed every scenario (exit 0), a nipple node
    # past the mesh failed after the first solve (a traceback), -1 meant the last node, a
    # mirror passed as a rotation
    import json

    from calib.sweep import CalibrationMissingError, load_sweep_model

    work = make_box_work(tmp_path / "work")
    path = work / "calibration.json"
    doc = json.loads(path.read_text())
    edit(doc["model"])
    path.write_text(json.dumps(doc))
    with pytest.raises((CalibrationMissingError, ValueError), match=says):
        load_sweep_model(work)


def test_a_sweep_that_solves_nothing_exits_2(tmp_path, monkeypatch):
    # review AD: "0 of 6 scenarios solved, 6 failed" exited 0
    import fem

    def never(*args, **kw):
        raise fem.ConvergenceError("simulated failure")

    monkeypatch.setattr(fem, "solve_posture", never)
    work = make_box_work(tmp_path / "work")
    args = ["sweep", str(work), "--out", str(tmp_path / "S"), "--plan", "sphere:6", "--serial"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "0 of 6 scenarios solved, 6 failed" in res.output
    assert "no scenario solved" in res.stderr and "simulated failure" in res.stderr


def test_a_sweep_says_which_model_it_solved(tmp_path):
    # review AX: the homogeneous calibration's sweep and a diagnosis refit's printed the
    # same lines, and nothing said that the diagnosis had named an effect elsewhere
    import json

    work = make_box_work(tmp_path / "work")
    c1 = json.loads((work / "calibration.json").read_text())["c1_pa"]
    args = ["sweep", str(work), "--out", str(tmp_path / "S"), "--plan", "sphere:6", "--serial"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert f"model: c1 {c1:.1f} Pa, homogeneous, neo-hookean (uncoupled), from {work}" in res.output
    assert "names" not in res.output
    (work / "diagnosis.json").write_text(json.dumps({"named": ["skin"]}))
    res = CliRunner().invoke(app, args)  # resumed: nothing pending, the same lines
    assert res.exit_code == 0, res.output
    # review AX: it said "0 solved in 0.0 s on pool (0 workers)"
    assert "6 of 6 scenarios solved, 0 failed, 0 pending; this run: nothing to solve" in res.output
    # review BT: the Newton statistics are the store's, solved by an earlier run
    assert (
        "  the store's cold starts: " in res.output or "  the store's warm starts: " in res.output
    )
    assert f"diagnosis.json names skin: {work / 'diagnosis' / 'refit'} holds" in res.output
