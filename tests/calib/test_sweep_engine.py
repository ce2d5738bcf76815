"""The sweep engine on a tiny calibrated block: physics, frames, store contents, resume."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nn"))
from sweep_helpers import BOX_C1_PA, make_box_work

import fem
from calib.sweep import CalibrationMissingError, load_sweep_model
from calib.sweep.store import CONVERGENCE_COLUMNS, StoreMismatchError
from calib.workflows.sweep import SweepOptions, run_sweep

PLAN = SweepOptions(plan="sphere:12", c1_axis="400:700:2", backend="serial", chunk_size=4)


def _read(store):
    import zarr

    g = zarr.open_group(store, mode="r")
    return {
        k: np.asarray(g[k][:])
        for k in (
            "results/displacement_mm",
            "results/tumour_mm",
            "results/nipple_mm",
            "results/status",
            "results/convergence",
            "results/state",
            "scenarios/gravity_phantom",
            "scenarios/gravity_ref",
            "scenarios/c1_pa",
            "scenarios/parent",
        )
    }, dict(g.attrs)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return make_box_work(tmp_path_factory.mktemp("sweep") / "work")


@pytest.fixture(scope="module")
def reference(work, tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "ref"
    summary = run_sweep(work, out, PLAN)
    return out, summary


def test_load_depends_on_rho_g_over_c1_only(work):
    # W = c1 (I1bar - 3) + kappa/2 (J-1)^2 with kappa ~ c1 at fixed nu: equilibrium
    # depends on rho g / c1 alone. Doubling both is exact in floating point (every
    # product scales by 2), so the iterates are the same; a factor 1.37 differs only by
    # the two Newton solves' convergence (rtol 1e-8 of the load, quadratic: the last
    # residuals are ~1e-12), far below 1e-7 mm on ~6 mm displacements.
    m = load_sweep_model(work)
    fm = m.fem_model()
    disc = fem.discretize(fm.mesh, fm.support, formulation=m.formulation)
    g = m.R_ref_from_phantom @ np.array([0.6, 0.0, 0.8])

    def solve(c1, g_m_s2):
        model = fm.with_material("bulk", fem.NeoHookean(c1, nu=m.nu))
        return fem.solve(model, gravity=g, g_m_s2=g_m_s2, disc=disc).displacement_mm

    u = solve(m.c1_pa, 9.81)
    assert np.linalg.norm(u, axis=1).max() > 1.5  # a finite load, not a vanishing one
    assert np.abs(solve(2 * m.c1_pa, 2 * 9.81) - u).max() <= 1e-12
    assert np.abs(solve(1.37 * m.c1_pa, 1.37 * 9.81) - u).max() <= 1e-7
    assert np.abs(solve(1.37 * m.c1_pa, 9.81) - u).max() > 0.5  # c1 alone does matter


def test_store_holds_the_fe_solutions(work, reference):
    out, summary = reference
    r, attrs = _read(out)
    assert summary["solved"] == 24 and summary["failed"] == summary["pending"] == 0
    assert attrs["status"] == "complete" and attrs["format"] == "phantom-calib.sweep"
    m = load_sweep_model(work)
    fm = m.fem_model()
    disc = fem.discretize(fm.mesh, fm.support, formulation=m.formulation)
    from fem.probe import MaterialPoint

    tumour = MaterialPoint.locate(disc, m.tumour_stress_free_mm)
    for i in (0, 5, 17):
        # an independent cold solve at the scenario's own c1 and the true gravity: the
        # phantom -> reference frame and the c1 -> gravity scaling of the store; a warm
        # and a cold Newton solve agree to their convergence (see the test above)
        c1, g_ph = r["scenarios/c1_pa"][i], r["scenarios/gravity_phantom"][i]
        assert np.allclose(r["scenarios/gravity_ref"][i], m.R_ref_from_phantom @ g_ph)
        model = fm.with_material("bulk", fem.NeoHookean(c1, nu=m.nu))
        sol = fem.solve(model, gravity=m.R_ref_from_phantom @ g_ph, g_m_s2=9.81, disc=disc)
        u = r["results/displacement_mm"][i]
        assert np.abs(u - sol.displacement_mm).max() <= 1e-7
        # tumour and nipple: material point of the stored state, two code paths
        x = r["results/state"][i]
        assert np.allclose(r["results/tumour_mm"][i], tumour.displacement_mm(x), atol=1e-12)
        via = fem.displacement_at(disc, x, m.tumour_stress_free_mm[None])[0]
        assert np.allclose(r["results/tumour_mm"][i], via, atol=1e-9)
        assert np.array_equal(r["results/nipple_mm"][i], u[m.nipple_node])
    conv = dict(zip(CONVERGENCE_COLUMNS, r["results/convergence"].T, strict=True))
    assert np.all(conv["newton_iterations"] >= 1) and np.all(conv["attempts"] == 1)
    assert np.array_equal(conv["warm_start"] == 1, r["scenarios/parent"] >= 0)
    assert np.all(conv["final_residual"] <= 1e-8)  # SolverOptions.rtol


def test_warm_starts_save_newton_iterations(work, tmp_path):
    s = run_sweep(
        work, tmp_path / "d", SweepOptions(plan="dissertation:transverse", backend="serial")
    )
    # 72 scenarios in chunks of 12: 6 cold starts at least, the other 66 warm where a
    # solved scenario of their chunk lies within 45 degrees (11 to 1 at most); 5 to 1
    # leaves room for a few without one
    assert s["warm"]["n"] > 5 * s["cold"]["n"]
    assert s["warm"]["newton_mean"] < s["cold"]["newton_mean"]


def test_interrupted_sweep_resumes_to_the_same_numbers(
    work, reference, tmp_path, monkeypatch, caplog
):
    import calib.io

    out = tmp_path / "s"
    seen = []

    def stop_after_five(ev):
        if not ev.get("start"):
            seen.append(ev["index"])
            if len(seen) == 5:
                raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sweep(work, out, PLAN, progress=stop_after_five)
    status = _read(out)[0]["results/status"]
    assert np.sum(status == 1) == 5 and not (out / ".lock").exists()
    # review BI: a resume by other code left the creating run's provenance alone; here
    # the resume runs as if from another commit
    first = _read(out)[1]["provenance"]
    monkeypatch.setattr(
        calib.io, "_source_revision", lambda: {"commit": "0" * 40, "uncommitted_edits": False}
    )
    with caplog.at_level("WARNING", logger="calib.workflows.sweep"):
        summary = run_sweep(work, out, PLAN)
    assert summary["this_run"]["solved"] == 19 and summary["solved"] == 24
    attrs = _read(out)[1]
    assert attrs["provenance"] == first  # the creating run's
    (resume,) = attrs["resumes"]
    assert resume["source"]["commit"] == "0" * 40 and resume["parameters"]["chunk_size"] == 4
    assert "differs from the one that created the store (another phantom-calib commit)" in (
        caplog.text
    )
    # the same warm starts from the same stored states: the same bits (1e-9 mm asked)
    a, b = _read(out)[0], _read(reference[0])[0]
    assert np.abs(a["results/displacement_mm"] - b["results/displacement_mm"]).max() <= 1e-9
    # a third run has nothing to do, and adds no record
    assert run_sweep(work, out, PLAN)["this_run"]["solved"] == 0
    assert len(_read(out)[1]["resumes"]) == 1


def test_a_damaged_store_is_named_on_resume(work, reference, tmp_path):
    # review AD: a corrupt status chunk gave the codec's words only, a missing
    # scenarios/parent a KeyError traceback
    import shutil

    import zarr

    from calib.sweep.store import StoreError

    out = tmp_path / "s"
    shutil.copytree(reference[0], out)
    chunk = out / "results" / "status" / "c" / "4"
    chunk.write_bytes(b"junk")
    with pytest.raises(StoreError, match=r"results/status: unreadable"):
        run_sweep(work, out, PLAN)
    shutil.rmtree(out)
    shutil.copytree(reference[0], out)
    zarr.open_group(out, mode="r+")["results/status"][3] = 0  # pending: resume reads parent
    shutil.rmtree(out / "scenarios" / "parent")
    with pytest.raises(StoreError, match=r"scenarios/parent"):
        run_sweep(work, out, PLAN)


def test_a_solved_scenario_whose_chunk_was_lost_is_solved_again(work, reference, tmp_path):
    # review AM: with one displacement chunk deleted, a re-run said "all solved" and did
    # nothing; it is pending again and solved to the same numbers
    import shutil

    import nn

    out = tmp_path / "s"
    shutil.copytree(reference[0], out)
    shutil.rmtree(out / "results" / "displacement_mm" / "c" / "5")
    with pytest.raises(nn.StoreFormatError, match="displacement_mm/c/5/0/0: missing"):
        nn.load_sweep(out)

    # review BF: the root status stayed "complete" while the lost scenario was pending;
    # a run killed then left it so
    def killed(ev):
        if ev.get("start"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sweep(work, out, PLAN, progress=killed)
    assert json.loads((out / "zarr.json").read_text())["attributes"]["status"] == "running"
    assert run_sweep(work, out, PLAN)["this_run"]["solved"] == 1
    assert json.loads((out / "zarr.json").read_text())["attributes"]["status"] == "complete"
    again, before = nn.load_sweep(out), nn.load_sweep(reference[0])
    assert np.array_equal(again.displacement_mm, before.displacement_mm)


def test_store_of_another_model_or_plan_is_refused(work, reference, tmp_path):
    out = reference[0]
    with pytest.raises(StoreMismatchError, match="another plan.*spec"):
        run_sweep(
            work,
            out,
            SweepOptions(plan="sphere:13", c1_axis="400:700:2", backend="serial", chunk_size=4),
        )
    other = make_box_work(tmp_path / "other", shift_mm=1.0)
    with pytest.raises(
        StoreMismatchError, match=r"zarr\.json: the store holds a sweep of another mesh"
    ):
        run_sweep(other, out, PLAN)
    stiffer = make_box_work(tmp_path / "stiffer", c1_pa=2 * BOX_C1_PA)
    # review BT: the message names what differs, with both values
    said = rf"another calibrated model \(model\.c1_pa: {BOX_C1_PA!r} in the store, "
    with pytest.raises(StoreMismatchError, match=said + rf"{2 * BOX_C1_PA!r} now\)"):
        run_sweep(stiffer, out, PLAN)


def test_a_seed_no_plan_draws_with_is_no_part_of_it(work, reference, tmp_path):
    # review AD: resuming with another --seed was refused where the plan draws nothing with
    # it (no hold-out): "another plan (seed: 0 != 1)"
    from dataclasses import replace

    out = reference[0]
    summary = run_sweep(work, out, replace(PLAN, seed=1))
    assert summary["this_run"]["solved"] == 0  # the same plan: nothing to do
    held = replace(PLAN, plan="sphere:12", holdout=0.25)
    run_sweep(work, tmp_path / "h", held)
    with pytest.raises(StoreMismatchError, match=r"another plan \(seed: 0 != 1\)"):
        run_sweep(work, tmp_path / "h", replace(held, seed=1))  # there it draws


def _skin_work(path, **values):
    from calib.model.effects import EffectValues

    v = EffectValues(nu=0.49, **values).as_json()  # make_box_work's nu
    return make_box_work(path, skin_above_mm=20.0, effects={"named": ["skin"], "values": v})


def test_a_diagnosis_refit_is_swept_with_its_effects(tmp_path):
    # review AT: a refit naming a skin was swept as the homogeneous body at the refitted
    # c1 (44 % more nipple displacement on the tiny twin), exit 0. Two code paths: the
    # store against independent solves of the library's effect model, at the calibrated
    # c1 and at another c1 of the axis (the skin's c1 is a ratio of the bulk's, so the
    # c1 -> gravity scaling holds; its tolerance as in test_store_holds_the_fe_solutions)
    from calib.model.effects import EffectValues, effect_model

    work = _skin_work(tmp_path / "work", skin_ratio=4.0)
    m = load_sweep_model(work)
    assert m.effects["named"] == ["skin"] and m.scales_with_c1
    out = tmp_path / "s"
    run_sweep(work, out, SweepOptions(plan="sphere:4", c1_axis="400:700:2", backend="serial"))
    r, attrs = _read(out)
    assert attrs["model"]["effects"]["named"] == ["skin"]
    assert attrs["model"]["effects"]["values"]["skin_ratio"] == 4.0
    assert len(attrs["model"]["effects"]["regions_sha256"]) == 64  # the tags are the model
    mesh = m.tet_mesh()
    assert sorted(mesh.region_names) == ["bulk", "skin"]
    disc = fem.discretize(mesh, fem.Clamped(), formulation=m.formulation)
    values = EffectValues(skin_ratio=4.0, nu=0.49)
    for i in range(len(r["scenarios/c1_pa"])):
        c1, g_ph = r["scenarios/c1_pa"][i], r["scenarios/gravity_phantom"][i]
        g = m.R_ref_from_phantom @ g_ph
        sol = fem.solve(effect_model(mesh, c1, values), gravity=g, g_m_s2=9.81, disc=disc)
        u = r["results/displacement_mm"][i]
        assert np.abs(u - sol.displacement_mm).max() <= 1e-7
        bare = fem.Model.homogeneous(mesh, fem.NeoHookean(c1, nu=0.49))
        homogeneous = fem.solve(bare, gravity=g, g_m_s2=9.81, disc=disc).displacement_mm
        assert np.abs(u - homogeneous).max() > 0.1  # the skin shows in the store


def test_a_refit_on_springs_has_no_c1_axis_and_bad_effects_are_named(tmp_path):
    from calib.sweep.plans import PlanError

    work = _skin_work(tmp_path / "springs", support_stiffness_pa_per_mm=300.0)
    assert not load_sweep_model(work).scales_with_c1
    with pytest.raises(
        PlanError, match=r"^c1_axis \(--c1\) .*tangential springs.*sweep without a c1 axis"
    ):
        run_sweep(work, tmp_path / "s", PLAN)
    assert not (tmp_path / "s").exists()
    run_sweep(work, tmp_path / "s", SweepOptions(plan="sphere:2", backend="serial"))
    # a named effect outside the library, and a skin named on a mesh without its region
    import json

    for edit, says in (
        (lambda d: d["model"]["effects"]["named"].append("gloss"), "not effects of the library"),
        (lambda d: d["model"]["effects"]["values"].update(skin_ratio=-1), "skin_ratio must be"),
        (lambda d: d["model"]["effects"]["values"].update(nu=0.45), "differs from model.nu"),
    ):
        w = _skin_work(tmp_path / f"w{len(says)}", skin_ratio=4.0)
        record = w / "calibration.json"
        doc = json.loads(record.read_text())
        edit(doc)
        record.write_text(json.dumps(doc))
        with pytest.raises(CalibrationMissingError, match=f"calibration.json: .*{says}"):
            load_sweep_model(w)
    values = {"named": ["skin"], "values": {"skin_ratio": 4.0, "nu": 0.49}}
    w = make_box_work(tmp_path / "noskin", effects=values)
    with pytest.raises(CalibrationMissingError, match="reference_mesh.vtu: no skin region"):
        load_sweep_model(w)


def test_a_store_inside_the_work_folder_s_calibration_is_refused(work):
    # review AT: the next calibrate deleted it (hours of FE on a real plan) without a word
    from calib.io import InsideRunFolderError

    with pytest.raises(InsideRunFolderError, match="replaces as a whole"):
        run_sweep(work, work / "calibration" / "store", PLAN)
    assert not (work / "calibration" / "store").exists()


def test_serial_with_workers_is_refused(work, tmp_path):
    # review AT: --serial --workers 7 ran on one worker without a word
    from typer.testing import CliRunner

    from calib.cli import app

    args = ["sweep", str(work), "--out", str(tmp_path / "s"), "--serial", "--workers", "7"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "solves in this process: drop workers (--workers)" in res.stderr
    # and the Python API alike (review AU)
    with pytest.raises(
        ValueError, match=r"^backend 'serial' \(--serial\) solves in this process: drop workers"
    ):
        SweepOptions(backend="serial", workers=4)
    assert not (tmp_path / "s").exists()


def test_missing_calibration_is_named(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(CalibrationMissingError, match=r"calibration\.json not found"):
        run_sweep(tmp_path / "empty", tmp_path / "s", PLAN)
    with pytest.raises(CalibrationMissingError, match="no such work folder"):
        run_sweep(tmp_path / "nowhere", tmp_path / "s", PLAN)
    (tmp_path / "calibration.json").write_text("{}")  # review AT: called no such folder
    with pytest.raises(CalibrationMissingError, match="is a file: pass the work folder"):
        run_sweep(tmp_path / "calibration.json", tmp_path / "s", PLAN)
    assert not (tmp_path / "s").exists()


def test_cli_sweep(work, tmp_path):
    from typer.testing import CliRunner

    from calib.cli import app

    runner = CliRunner()
    res = runner.invoke(
        app, ["sweep", str(work), "--out", str(tmp_path / "s"), "--plan", "sphere:6", "--serial"]
    )
    assert res.exit_code == 0, res.output
    assert "6 of 6 scenarios solved" in res.output and "Newton iterations per solve" in res.output
    res = runner.invoke(app, ["sweep", str(tmp_path), "--out", str(tmp_path / "t")])
    assert res.exit_code == 2 and "calibration.json not found" in res.output
    res = runner.invoke(app, ["sweep", str(work), "--out", str(tmp_path / "t"), "--plan", "ring"])
    assert res.exit_code == 2 and "unknown plan (--plan)" in res.output
    res = runner.invoke(
        app, ["sweep", str(work), "--out", str(tmp_path / "s"), "--plan", "sphere:7", "--serial"]
    )
    assert res.exit_code == 2 and "another plan" in res.output


class _FakeStore:
    path = Path("store")

    def __init__(self, first):
        self.attrs, self.records = ({"provenance": first} if first is not None else {}), []

    def record_resume(self, record):
        self.records.append(record)


@pytest.mark.parametrize(
    ("first", "now", "said"),
    [
        # review BK: an older store's record (no source, fewer packages) is not compared
        ({"versions": {}}, {"commit": "a", "uncommitted_edits": False}, None),
        (None, {"commit": "a", "uncommitted_edits": False}, None),
        # only the FE's libraries are compared (torch sets no sweep number)
        (
            {"source": {"commit": "a", "uncommitted_edits": False}, "versions": {"torch": "0"}},
            {"commit": "a", "uncommitted_edits": False},
            None,
        ),
        (
            {"source": {"commit": "a", "uncommitted_edits": False}, "versions": {"numpy": "0"}},
            {"commit": "a", "uncommitted_edits": False},
            "other versions of numpy",
        ),
        # the same commit with edits may be other code
        (
            {"source": {"commit": "a", "uncommitted_edits": True}},
            {"commit": "a", "uncommitted_edits": False},
            "uncommitted edits in a run",
        ),
        # review BT, F12: the same edits (one digest) are the same code; others are not
        (
            {"source": {"commit": "a", "uncommitted_edits": True, "edits_sha256": "d1"}},
            {"commit": "a", "uncommitted_edits": True, "edits_sha256": "d1"},
            None,
        ),
        (
            {"source": {"commit": "a", "uncommitted_edits": True, "edits_sha256": "d1"}},
            {"commit": "a", "uncommitted_edits": True, "edits_sha256": "d2"},
            "uncommitted edits in a run",
        ),
        (  # an older record without a digest
            {"source": {"commit": "a", "uncommitted_edits": True}},
            {"commit": "a", "uncommitted_edits": True, "edits_sha256": "d1"},
            "uncommitted edits in a run",
        ),
        ({"source": {"commit": "a", "uncommitted_edits": False}}, None, "installed in the other"),
    ],
)
def test_a_resume_is_recorded_and_said_only_where_its_code_may_differ(
    first, now, said, monkeypatch, caplog
):
    from types import SimpleNamespace

    import calib.io
    from calib.workflows.sweep import _record_resume

    monkeypatch.setattr(calib.io, "_source_revision", lambda: now)
    store = _FakeStore(first)
    with caplog.at_level("WARNING", logger="calib.workflows.sweep"):
        _record_resume(store, PLAN, SimpleNamespace(source={}))
    (record,) = store.records
    assert record["source"] == now and record["parameters"]["plan"] == "sphere:12"
    if said is None:
        assert not caplog.records
    else:
        (warning,) = caplog.records
        assert said in warning.getMessage()


def test_a_failure_at_an_element_the_reference_holds_inverted_says_so(work):
    # review BP, P3: an independent generator's calibration holds 9 elements inverted at
    # the clamped rim; its scenarios at and near the reference posture failed at one of
    # them, with fem's words "the load may be too large for the material", and nothing
    # pointed at the recovered reference
    import dataclasses

    import fem
    from calib.sweep.engine import _flipped_note

    model = load_sweep_model(work)
    assert len(model.flipped_elements) == 0  # the box: one orientation
    tets = model.tets.copy()
    tets[[3, 7]] = tets[[3, 7]][:, [1, 0, 2, 3]]  # two elements turned inside out
    folded = dataclasses.replace(model, tets=tets)
    assert folded.flipped_elements.tolist() == [3, 7]
    at = fem.ConvergenceError("load not applied: ... (element 7, ...)", element=7)
    note = _flipped_note(folded, at)
    assert "element 7 is one of the 2 the stress-free reference holds inverted" in note
    assert "--reference-state prestress" in note
    assert _flipped_note(folded, fem.ConvergenceError("x", element=5)) == ""
    assert _flipped_note(folded, fem.ConvergenceError("no step converged")) == ""
    assert _flipped_note(folded, ValueError("x")) == ""


def test_a_prestressed_model_s_provenance_names_the_files_it_is_solved_on(tmp_path):
    # review BT: a prestressed reference is solved on the loaded mesh and its inverse state,
    # but the store's provenance named the stress-free reference_mesh.vtu as its input
    import shutil

    from calib.sweep import load_sweep_model

    work = make_box_work(tmp_path / "work")
    cal = work / "calibration"
    shutil.copy(cal / "reference_mesh.vtu", cal / "loaded_reference_mesh.vtu")
    np.savez(cal / "reference_prestress.npz", inverse_state=np.zeros(3), gravity_m_s2=[0, 0, 9.81])
    doc = json.loads((work / "calibration.json").read_text())
    doc["model"]["prestress"] = {
        "mesh": "calibration/loaded_reference_mesh.vtu",
        "state": "calibration/reference_prestress.npz",
    }
    (work / "calibration.json").write_text(json.dumps(doc))
    assert sorted(load_sweep_model(work).source) == [
        "calibration.json",
        "loaded_reference_mesh.vtu",
        "reference_prestress.npz",
    ]
    assert sorted(load_sweep_model(make_box_work(tmp_path / "plain")).source) == [
        "calibration.json",
        "reference_mesh.vtu",
    ]


def test_a_lock_of_another_host_is_refused_and_a_dead_one_here_taken_over(work, tmp_path):
    # review BT: the lock held a bare pid, which a run on another host of a shared file
    # system read as dead, and took over the lock of a store being written
    import shutil

    from calib.sweep.store import StoreLockedError

    out = tmp_path / "s"
    run_sweep(work, out, PLAN)
    (out / ".lock").write_text("node17.cluster:4242")
    with pytest.raises(StoreLockedError, match=r"process 4242 on host node17\.cluster holds"):
        run_sweep(work, out, PLAN)
    assert (out / ".lock").read_text() == "node17.cluster:4242"
    (out / ".lock").write_text(str(2**22 + 17))  # a bare pid (older versions), no process
    assert run_sweep(work, out, PLAN)["pending"] == 0 and not (out / ".lock").exists()
    shutil.rmtree(out)


def test_a_store_swept_with_another_support_node_set_is_refused(work, tmp_path, monkeypatch):
    # review BT: the model key covers the mesh and the physics, not the clamped node set:
    # a resume with half the back nodes would have solved on another support unseen
    from dataclasses import replace as with_

    import calib.sweep
    from calib.sweep.store import StoreMismatchError

    out = tmp_path / "s"
    run_sweep(work, out, PLAN)
    real = calib.sweep.load_sweep_model

    def half_the_back(w):
        model = real(w)
        return with_(model, back_nodes=model.back_nodes[: len(model.back_nodes) // 2])

    monkeypatch.setattr(calib.sweep, "load_sweep_model", half_the_back)
    with pytest.raises(StoreMismatchError, match=r"another node set mesh/back_nodes"):
        run_sweep(work, out, PLAN)


def test_progress_lines_give_a_notebook_text_from_the_sweep_s_events():
    # review BW, F5: progress=print printed the sweep's raw dicts; the other stages' lines
    import doctest

    import calib.sweep.progress
    from calib.sweep import progress_lines

    assert doctest.testmod(calib.sweep.progress).failed == 0
    lines = []
    cb = progress_lines(lines.append)
    cb({"start": True, "done": 0, "total": 40})  # about every 5 %: every 2nd
    ev = {"ok": True, "newton_iterations": 3, "wall_s": 0.25, "worker": "w", "message": ""}
    for k in range(1, 41):
        ok = k != 7
        cb(ev | {"done": k, "total": 40, "index": 100 + k, "ok": ok, "message": "no FE"})
    assert lines[0] == "sweep: 40 scenarios to solve"
    assert "7/40: scenario 107 FAILED: no FE" in lines
    assert len(lines) == 1 + 20 + 1 and lines[-1].startswith("40/40: scenario 140 solved, 3 ")
    with pytest.raises(ValueError, match="every must be a positive number"):
        progress_lines(print, every=0)


def test_what_is_no_sweep_store_is_named_and_left_as_it_was(work, reference, tmp_path):
    # review CG-8: these refusals had no test. A folder of the user's (not a store), with
    # and without --overwrite; a store of another format, another format version, and one
    # with an array gone: each named, nothing changed
    import shutil
    from dataclasses import replace

    from calib.sweep.store import StoreError

    mine = tmp_path / "notes"
    mine.mkdir()
    (mine / "mine.txt").write_text("mine")
    with pytest.raises(StoreError, match=r"zarr\.json not found: .*notes is not a sweep store"):
        run_sweep(work, mine, PLAN)
    with pytest.raises(StoreError, match=r"notes: not a sweep store; overwrite \(--overwrite\)"):
        run_sweep(work, mine, replace(PLAN, overwrite=True))
    assert [p.name for p in mine.iterdir()] == ["mine.txt"]
    out = tmp_path / "s"
    shutil.copytree(reference[0], out)
    meta = out / "zarr.json"
    doc = json.loads(meta.read_text())

    def files():  # every file of the store with its bytes (review CH-12: "nothing changed")
        return {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}

    for attrs, said in (
        ({"format": "another"}, r"not a \S+ store \(an interrupted creation, or another kind"),
        ({"format_version": 999}, r"format version 999, this phantom-calib reads"),
    ):
        meta.write_text(json.dumps(doc | {"attributes": doc["attributes"] | attrs}))
        before = files()
        with pytest.raises(StoreError, match=said):
            run_sweep(work, out, PLAN)
        assert files() == before
    meta.write_text(json.dumps(doc))
    shutil.rmtree(out / "results" / "nipple_mm")
    before = files()
    with pytest.raises(StoreError, match=r"s: array .*nipple_mm.* missing \(truncated store\)"):
        run_sweep(work, out, PLAN)
    assert files() == before
