"""Runs as runs (``calib/io.py``, review AN): locks, records of a replaced fit, provenance."""

import json
import os
from pathlib import Path

import pytest


def test_a_calibration_whose_scans_were_ingested_again_meanwhile_writes_nothing(tmp_path):
    # review AN: the record took the scans' run id at its end, so an ingest during the fit
    # was recorded as the one fitted; the check comes before anything is read or written
    from calib.io import StaleOutputError, write_json_atomic
    from calib.workflows.calibrate import write_calibration

    write_json_atomic(tmp_path / "scans" / "RUN", {"run_id": "during"})
    with pytest.raises(StaleOutputError, match="ingested again during this calibration"):
        write_calibration(tmp_path, None, {}, inputs={}, wall_s=0.0, ingest_run_id="before")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scans"]


def test_a_new_calibration_removes_the_validation_of_the_old_one(tmp_path, caplog):
    # review AN: a calibrate stopped in its closing validate left the old fit's report;
    # a diagnosis of it stays (review AP: 35 minutes of work; the view checks its run id)
    from calib.workflows.calibrate import _drop_outputs_of_another_fit

    for name in ("validation", "diagnosis"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "report.html").write_text("...")
        (tmp_path / f"{name}.json").write_text(json.dumps({"calibration_run_id": "old"}))
    _drop_outputs_of_another_fit(tmp_path, "new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diagnosis", "diagnosis.json"]
    assert "validation.json and" in caplog.text
    caplog.clear()
    _drop_outputs_of_another_fit(tmp_path, "new")  # nothing to remove: nothing said
    assert caplog.text == ""
    # a validation made from the new calibration stays, without a word (review CG-2: the
    # keeping was never tested; removing on every call passed)
    (tmp_path / "validation").mkdir()
    (tmp_path / "validation.json").write_text(json.dumps({"calibration_run_id": "new"}))
    _drop_outputs_of_another_fit(tmp_path, "new")
    assert (tmp_path / "validation").is_dir() and (tmp_path / "validation.json").is_file()
    assert caplog.text == ""


@pytest.mark.parametrize("kind", ["folder", "file"])
def test_a_run_folder_s_place_holding_what_no_run_wrote_is_refused_and_kept(
    tmp_path, kind, monkeypatch
):
    # review CG-7: a user's own WORK/calibration/ (notes) went with the first calibrate,
    # which swaps its folder in whole; now refused, before the work, the files untouched
    from calib_helpers import make_scan_folder

    from calib.io import ForeignFolderError, RunOutputs
    from calib.workflows.calibrate import run_calibration
    from calib.workflows.ingest import run_ingest

    scans, work = make_scan_folder(tmp_path / "scans"), tmp_path / "work"
    mine = work / "calibration"
    if kind == "folder":
        mine.mkdir(parents=True)
        (mine / "my_notes.txt").write_text("mine")
    else:
        work.mkdir()
        mine.write_text("mine")
    with pytest.raises(ForeignFolderError, match=r"calibration is a (folder no phantom-calib "
                       r"run wrote|file).*replaces calibration/ as a whole"):  # fmt: skip
        RunOutputs(work, folder="calibration", record="calibration.json")
    # calibrate refuses before it reads a scan (the placeholders would fail to read)
    with pytest.raises(ForeignFolderError, match="phantom-calib calibrate"):
        run_calibration(scans, work, None)
    (work / "scans").mkdir()
    (work / "scans" / "mine.nii.gz").write_text("mine")
    with pytest.raises(ForeignFolderError, match=r"scans is a folder.*phantom-calib ingest"):
        run_ingest(scans, work)
    assert (mine / "my_notes.txt" if kind == "folder" else mine).read_text() == "mine"
    assert sorted(p.name for p in work.iterdir()) == ["calibration", "scans"]
    # validate and diagnose ask before their work too (their work a recorder: not run;
    # the stub work folder lets them reach it, review CH-11)
    from calib_helpers import stub_work_commands

    worked = []
    for folder, run in stub_work_commands(monkeypatch, worked):
        (work / folder).mkdir()
        (work / folder / "mine.txt").write_text("mine")
        with pytest.raises(ForeignFolderError, match=rf"^WORK .*{folder} is a folder no phantom"):
            run(work)
        assert (work / folder / "mine.txt").read_text() == "mine"
    assert worked == []


def test_a_link_in_a_run_folder_s_place_is_refused_and_calibrate_asks_about_validation(tmp_path):
    # review CH-3: a link was called "lost"; the run would put a folder in its place
    from typer.testing import CliRunner

    from calib.cli import app
    from calib.io import ForeignFolderError, RunOutputs

    elsewhere, work = tmp_path / "elsewhere", tmp_path / "work"
    elsewhere.mkdir()
    work.mkdir()
    (work / "calibration").symlink_to(elsewhere)
    said = r"calibration is a link \(to .*elsewhere\); `phantom-calib calibrate` writes"
    with pytest.raises(ForeignFolderError, match=said + " calibration/ as a folder of its own"):
        RunOutputs(work, folder="calibration", record="calibration.json")
    assert (work / "calibration").is_symlink()
    # the command validates after its fit: a validation/ no run wrote is refused first
    (work / "calibration").unlink()
    (work / "validation").mkdir()
    (work / "validation" / "mine.txt").write_text("mine")
    res = CliRunner().invoke(app, ["calibrate", str(tmp_path / "no-session"), "--out", str(work)])
    assert res.exit_code == 2
    assert "validation is a folder no phantom-calib run wrote" in res.stderr
    assert "`phantom-calib calibrate` replaces validation/ as a whole" in res.stderr
    assert sorted(p.name for p in work.iterdir()) == ["validation"]


def test_each_folder_is_named_with_its_own_command(tmp_path):
    # review of 207bac7: the command of the first folder checked named the later ones too
    from calib.io import ForeignFolderError, check_replaceable

    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "RUN").write_text('{"run_id": "a"}')  # a run's: passes
    (tmp_path / "diagnosis").write_text("mine")
    with pytest.raises(ForeignFolderError, match="`phantom-calib diagnose` replaces diagnosis/"):
        check_replaceable(tmp_path, ("scans", "diagnosis"))


def test_a_run_folder_with_its_marker_its_record_or_nothing_in_it_is_replaced(tmp_path):
    from calib.io import RunOutputs, write_json_atomic

    for case in ("marker", "record", "empty"):
        work = tmp_path / case
        (work / "calibration").mkdir(parents=True)
        if case == "marker":
            write_json_atomic(work / "calibration" / "RUN", {"run_id": "old"})
        elif case == "record":  # an interrupted run's, or an older version's
            (work / "calibration" / "old.vtu").write_text("...")
            (work / "calibration.json").write_text("{}")
        with RunOutputs(work, folder="calibration", record="calibration.json") as run:
            run.path("new.txt").write_text("new")
            run.commit({})
        assert sorted(p.name for p in (work / "calibration").iterdir()) == ["RUN", "new.txt"]


def test_the_lock_is_reentrant_and_a_refused_input_leaves_no_folder(tmp_path):
    from calib.io import locking_work, work_lock

    @locking_work("ingest", create=True)
    def refuse(work):
        with work_lock(work, "nested"):  # the same process: re-entrant
            raise ValueError("bad session.toml")

    with pytest.raises(ValueError, match="bad session"):
        refuse(tmp_path / "a" / "work")
    assert not (tmp_path / "a").exists()  # neither WORK nor the parent made for it


def test_another_thread_of_the_process_is_refused_as_another_process_is(tmp_path):
    # closing notes: the re-entrance let a second thread of one process (two calls of
    # calib.calibrate from a thread pool in a notebook) write the same WORK at once
    import threading

    from calib.io import WorkBusyError, work_lock

    said = []

    def other():
        try:
            with work_lock(tmp_path, "validate"):
                said.append("entered")
        except WorkBusyError as exc:
            said.append(str(exc))

    with work_lock(tmp_path, "calibrate"):
        t = threading.Thread(target=other)
        t.start()
        t.join()
        with work_lock(tmp_path, "ingest"):  # this thread: re-entrant still
            pass
    assert len(said) == 1 and "calibrate, another thread" in said[0], said
    t = threading.Thread(target=other)  # released: the other thread takes it
    t.start()
    t.join()
    assert said[1:] == ["entered"]


def test_an_out_inside_a_work_folder_s_run_folder_is_refused(tmp_path):
    # review AT: a sweep store (or a simulate result) written into WORK/calibration/ went
    # with the next calibrate, which replaces that folder whole, without a word
    from calib.io import InsideRunFolderError, check_out_file, check_out_folder

    work = tmp_path / "work"
    for folder, record in (("calibration", "calibration.json"), ("diagnosis", "diagnosis.json")):
        (work / folder).mkdir(parents=True)
        (work / record).write_text("{}")
    with pytest.raises(InsideRunFolderError, match=r"calibration, which the next `phantom-c"):
        check_out_folder(work / "calibration" / "store")
    with pytest.raises(InsideRunFolderError, match="`phantom-calib diagnose` of"):
        check_out_file(work / "diagnosis" / "refit" / "calibration" / "mine.vtu")
    with pytest.raises(InsideRunFolderError, match="calibrate"):
        check_out_folder(work / "calibration")
    check_out_folder(work / "sweeps" / "store")  # beside the run folders: fine
    (work / "validation").mkdir()  # a folder of that name without its record: not a run's
    check_out_file(work / "validation" / "x.vtu")
    check_out_folder(tmp_path / "twin" / "scans")  # a scan folder named scans
    # review AU: ".." out of a run folder was refused, a link into one accepted
    check_out_file(work / "calibration" / ".." / "x.vtu")
    (tmp_path / "link").symlink_to(work / "calibration")
    with pytest.raises(InsideRunFolderError, match="calibration, which the next"):
        check_out_folder(tmp_path / "link" / "store")


def test_taking_the_lock_removes_what_killed_runs_of_any_command_left(tmp_path):
    # review AN: a killed calibrate's staging folder stayed until a later calibrate reached
    # its write step (a validate or diagnose in between left it); under the lock no other
    # command writes WORK, so any dead run's temporaries go. What is not a dead run's
    # stays (review AR): a live process's, one whose number no process can have (it
    # raised OverflowError and left the lock held), another file's atomic temporary (a
    # screenshot `calibration.png` is written beside the `calibration` folder).
    import subprocess
    import sys

    from calib.io import _HELD, work_lock

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    left = [f".calibration.staging-{dead.pid}", f".diagnosis.old-{dead.pid}"]
    kept = [f".validation.staging-{os.getpid()}", ".scans.staging-4294967296"]
    for name in [*left, *kept]:
        (tmp_path / name).mkdir()
    (tmp_path / ".calibration.k2x9_a.tmp.json").write_text("{")
    (tmp_path / ".calibration.q7w1b.tmp.png").write_bytes(b"")
    kept.append(".calibration.q7w1b.tmp.png")
    with work_lock(tmp_path, "validate"):
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted([".lock", *kept])
    assert tmp_path.resolve() not in _HELD and not (tmp_path / ".lock").exists()


def test_provenance_can_run_the_command_again(tmp_path, monkeypatch):
    # review AN: relative input paths and no working folder; no commit, no thread counts
    from calib.io import provenance

    monkeypatch.chdir(tmp_path)
    Path("in.txt").write_text("x")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    p = provenance(inputs={"input": "in.txt"})
    assert p["inputs"]["input"]["path"] == str(tmp_path / "in.txt")
    assert p["cwd"] == os.getcwd() and p["threads"]["OMP_NUM_THREADS"] == "1"
    repo = Path(__file__).resolve().parents[2]
    if (repo / ".git").exists():  # a source checkout (CI's clone is one)
        assert len(p["source"]["commit"]) == 40
        assert isinstance(p["source"]["uncommitted_edits"], bool)


@pytest.mark.parametrize(
    ("argv", "kernel", "entry"),
    [
        (["/venv/bin/phantom-calib", "calibrate", "scans", "work"], False, "phantom-calib"),
        (["/home/u/run_all.py", "--fast"], False, "python"),
        (["/venv/lib/ipykernel_launcher.py", "-f", "/run/kernel-1.json"], True, "jupyter kernel"),
    ],
)
def test_provenance_says_whether_its_command_can_be_run_again(monkeypatch, argv, kernel, entry):
    # review BI: in a notebook `command` is the kernel's launcher, which runs nothing again
    import sys
    import types

    from calib.io import provenance

    monkeypatch.setattr(sys, "argv", argv)
    if kernel:
        monkeypatch.setitem(sys.modules, "ipykernel", types.ModuleType("ipykernel"))
    else:
        monkeypatch.delitem(sys.modules, "ipykernel", raising=False)
    p = provenance()
    assert p["command"] == argv and p["entry"] == entry


def test_provenance_names_the_libraries_and_thread_counts_that_set_the_numbers():
    # review BI: mkl (PARDISO's last bits), the ingest chain, torch and zarr were missing
    # from `versions`, and `threads` held the environment only (null where unset)
    from importlib import metadata

    import numpy as np  # noqa: F401  (its BLAS is loaded: threadpoolctl sees it)

    from calib.io import provenance

    p = provenance()
    for name in ("mkl", "SimpleITK", "pydicom", "scikit-image", "trimesh", "torch", "zarr"):
        assert name in p["versions"], name
    assert p["versions"]["SimpleITK"] == metadata.version("SimpleITK")  # a dependency
    from threadpoolctl import threadpool_info  # a dependency

    pools = p["thread_pools"]
    assert pools["cpu_count"] == os.cpu_count()
    # one entry per library (review BK: by API, two OpenMP runtimes were one)
    assert set(pools["pools"]) == {lib["prefix"] for lib in threadpool_info()}
    for lib in threadpool_info():
        entry = pools["pools"][lib["prefix"]]
        assert entry["api"] == lib["internal_api"] and entry["num_threads"] >= 1


def test_the_source_revision_tells_one_tree_s_edits_from_another_s(tmp_path):
    # review BT, F12: every resume from an edited checkout warned that its code may differ;
    # a digest of the edits tells the same edited tree from another
    import subprocess

    from calib.io import _source_revision

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "a")
    clean = _source_revision(tmp_path)
    assert clean["uncommitted_edits"] is False and "edits_sha256" not in clean
    (tmp_path / "a.py").write_text("x = 2\n")
    (tmp_path / "untracked.txt").write_text("not code")  # not an edit to the tree
    one, again = _source_revision(tmp_path), _source_revision(tmp_path)
    assert one["uncommitted_edits"] and one == again and one["commit"] == clean["commit"]
    # review BV, F3: the user's diff settings (an external tool that prints nothing, colour,
    # no prefixes) neither blank the digest nor change it
    (tmp_path / "quiet.sh").write_text("#!/bin/sh\nexit 0\n")
    (tmp_path / "quiet.sh").chmod(0o755)
    git("config", "diff.external", str(tmp_path / "quiet.sh"))
    git("config", "color.diff", "always")
    git("config", "diff.noprefix", "true")
    assert _source_revision(tmp_path) == one
    (tmp_path / "a.py").write_text("x = 3\n")
    other = _source_revision(tmp_path)
    assert other["edits_sha256"] != one["edits_sha256"]


def test_an_interrupted_command_says_what_was_kept(monkeypatch, capsys):
    # review AN, AM: typer turns Ctrl-C into a silent exit 130
    import importlib

    cli = importlib.import_module("calib.cli.app")  # calib.cli.app is also the Typer

    def interrupted(args, prog_name):
        raise SystemExit(130)

    monkeypatch.setattr(cli, "app", interrupted)
    for command, says in (
        ("validate", "the step that was running kept nothing"),
        ("sweep", "the scenarios solved so far are kept in the store; run the same command"),
    ):
        with pytest.raises(SystemExit) as ended:
            cli.main([command, "w"])
        assert ended.value.code == 130  # the shell's Ctrl-C status kept (review CG-14)
        # the whole line (review CH-10: substrings were checked)
        kept = cli._INTERRUPTED.get(command, cli._KEPT_NOTHING)
        assert capsys.readouterr().err == f"\ninterrupted: {kept}\n" and kept.startswith(says)


def test_a_file_system_without_flock_runs_unlocked_and_says_so(tmp_path, monkeypatch, caplog):
    # review AP: a mount that refuses flock (some NFS, CIFS) stopped every command
    import errno
    import fcntl

    from calib.io import work_lock

    def refuse(f, how):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", refuse)
    with work_lock(tmp_path, "validate"):
        pass
    assert "not locked" in caplog.text and not (tmp_path / ".lock").exists()


def test_ingest_fingerprints_its_sources_before_it_reads_them(tmp_path, monkeypatch):
    # review BI: the sources were hashed after the scans were processed, so a source
    # changed during ingest was recorded with its new bytes and its results (made from the
    # old ones) were called current by calibrate
    from calib_helpers import make_scan_folder

    import calib.workflows.ingest as ingest

    calls = []
    real = ingest.ingest_inputs

    def inputs(session):
        calls.append("fingerprint")
        return real(session)

    def scans(session, progress=None):
        calls.append("read the scans")
        raise RuntimeError("stop here")

    monkeypatch.setattr(ingest, "ingest_inputs", inputs)
    monkeypatch.setattr(ingest, "ingest_scans", scans)
    with pytest.raises(RuntimeError, match="stop here"):
        ingest.run_ingest(make_scan_folder(tmp_path / "scans"), tmp_path / "work")
    assert calls == ["fingerprint", "read the scans"]


def test_hand_edited_or_truncated_run_markers_and_records_are_named(tmp_path):
    # review CG-10: these refusals had no test
    from calib.io import StaleOutputError, check_run, run_id_of

    (tmp_path / "calibration").mkdir()
    marker = tmp_path / "calibration" / "RUN"
    marker.write_text('{"run_id": "2026')  # truncated
    with pytest.raises(StaleOutputError, match=r"calibration/RUN: not a run marker"):
        run_id_of(tmp_path / "calibration")
    marker.write_text('["a list"]')  # valid JSON, not a marker
    with pytest.raises(StaleOutputError, match=r"calibration/RUN: not a run marker"):
        run_id_of(tmp_path / "calibration")
    record = tmp_path / "calibration.json"
    record.write_text("[1, 2]")
    with pytest.raises(StaleOutputError, match=r"calibration\.json: expected a JSON object "
                       r"\(the command's record\), got list"):  # fmt: skip
        check_run(tmp_path, folder="calibration", record="calibration.json")
    record.write_text('{"run_id": "a"')
    with pytest.raises(StaleOutputError, match=r"calibration\.json: not valid JSON"):
        check_run(tmp_path, folder="calibration", record="calibration.json")
