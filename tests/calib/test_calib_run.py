"""``phantom-calib calibrate`` end to end on a small twin: the public output contract.

The twin (two lateral postures and a 50 deg validation tilt, 14 mm phantom, 2 mm voxels)
keeps this in the default suite; the accuracy of the calibration is tested on FE-made
measurements in test_calib_calibrate.py and measured on the full presets by
benchmarks/bench_calib.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from calib_helpers import SMALL_VALIDATION_PRESET
from typer.testing import CliRunner

import calib.fitting.optimise
import calib.fitting.profile
import calib.model.forward
import fem
from calib.cli import app
from calib.twin import synthesize


@pytest.fixture(scope="module")
def twin_scans(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "twin"
    synthesize(out, preset=SMALL_VALIDATION_PRESET, seed=3)
    return out / "scans"


def _calibrate(scans, work, *args):
    res = CliRunner().invoke(app, ["calibrate", str(scans), "--out", str(work), *args])
    assert res.exit_code == 0, res.output
    return json.loads((work / "calibration.json").read_text()), res.output, work


@pytest.fixture(scope="module")
def nipple_run(twin_scans, tmp_path_factory):
    # Default mesh sizes (12 mm, retried at 14 and 16 mm when the reference cannot be
    # unloaded); the 12 mm recovery is made to fail here, so the retry path is exercised
    # and the run uses the 14 mm mesh (the size the homogeneous twin needs).
    real = calib.fitting.optimise._check_reference

    def fail_on_12(cal, theta0, progress):
        if cal.options.mesh_size_mm == 12.0:
            raise fem.ConvergenceError("inverse Newton stopped at load factor 0.8 (test)")
        real(cal, theta0, progress)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(calib.fitting.optimise, "_check_reference", fail_on_12)
        return _calibrate(twin_scans, tmp_path_factory.mktemp("work"), "--objective", "nipple")


def test_failed_mesh_size_is_reported_and_retried(nipple_run):
    doc, output, _ = nipple_run
    assert doc["mesh"]["size_mm"] == 14.0
    (failed,) = doc["mesh"]["failed_sizes"]
    assert failed["mesh_size_mm"] == 12.0 and "load factor 0.8" in failed["failure"]
    assert "trying the next size" in output


# calibration.json of phantom-calib 0.1 (before the library issue): its keys stay, new
# ones are only added (schema_version 1 adds schema_version, run_id, optimiser, model,
# model_fit; uncertainty adds interval; each scan adds model and its nominal posture).
KEYS_0_1 = {"c1_pa", "c1_ci95_pa", "objective", "objective_value_mm2", "reference_state",
            "uncertainty", "frames", "scans", "iterations", "fe_solves", "reference_recovery",
            "history", "profile", "mesh", "wall_s", "provenance"}  # fmt: skip
KEYS_ADDED = {"schema_version", "run_id", "optimiser", "model", "model_fit", "ingest_run_id",
              "scans_source"}  # fmt: skip
SCAN_KEYS_0_1 = {"role", "gravity_ref", "nipple_error_mm", "nipple_landmark_error_mm",
                 "surface_error_mm", "icp", "tumour_error_mm", "files"}  # fmt: skip
UNCERTAINTY_KEYS_0_1 = {"se_ln_c1", "c1_ci95_pa", "residual_sd_mm", "n_residuals",
                        "n_effective", "correlation_length_mm", "method", "mesh_check"}  # fmt: skip
MESH_KEYS_0_1 = {"n_tets", "n_nodes", "size_mm", "failed_sizes", "formulation"}
# the clamped back face (review U); the body's height in the mesh's elements (review BN)
MESH_KEYS_ADDED = {"support", "height_mm", "elements_in_height"}


def test_calibration_json_keys_are_those_of_0_1_plus_the_documented_additions(nipple_run):
    doc, _, _ = nipple_run
    assert set(doc) == KEYS_0_1 | KEYS_ADDED
    assert doc["schema_version"] == 1
    for name, scan in doc["scans"].items():
        assert set(scan) == SCAN_KEYS_0_1 | {"model", "posture"}, name
    assert doc["scans"]["right_lateral"]["posture"] == {"plane": "transverse", "angle_deg": 180.0}
    assert doc["model"]["reference_posture"] == {"plane": "transverse", "angle_deg": 0.0}
    assert set(doc["uncertainty"]) == UNCERTAINTY_KEYS_0_1 | {"interval"}
    assert doc["model_fit"] is None  # the misfit test is the surface objective's
    assert set(doc["mesh"]) == MESH_KEYS_0_1 | MESH_KEYS_ADDED
    mesh = doc["mesh"]  # the small twin, about 60-75 mm tall, on its 14 mm retry mesh
    assert mesh["elements_in_height"] == pytest.approx(mesh["height_mm"] / mesh["size_mm"])
    assert 4.0 < mesh["elements_in_height"] < 6.5 and 55.0 < mesh["height_mm"] < 80.0
    support = doc["mesh"]["support"]
    assert support["back_tol_mm"] == 1.0  # the twin's flat face: the default tolerance
    assert support["surface"] == "decimated"  # and TetGen takes its decimated surface
    assert 0.8 * support["plate_mm2"] <= support["clamped_mm2"]  # SUPPORT_AREA_SHARE
    assert {"success", "message", "iterations", "bound"} <= set(doc["optimiser"])


def test_calibration_json_contract(nipple_run):
    doc, output, _ = nipple_run
    for key in ("c1_pa", "c1_ci95_pa", "objective", "reference_state", "scans", "iterations",
                "fe_solves", "wall_s", "provenance", "history", "profile"):  # fmt: skip
        assert key in doc, key
    assert doc["objective"] == "nipple" and doc["reference_state"] == "unload"
    scan = doc["scans"]["right_lateral"]
    assert set(scan["surface_error_mm"]) == {"fiducial", "icp"}
    assert {"mean", "sd", "p95", "max"} <= set(scan["surface_error_mm"]["fiducial"])
    assert set(scan["nipple_error_mm"]) == {"fiducial", "icp"}
    assert "c1 =" in output and "95 % interval" in output


def test_nipple_objective_has_a_profile_interval(nipple_run):
    # Issue 6: a 95 % interval for every objective. The nipple residual is flat in c1 at
    # its optimum, so the interval comes from the likelihood profile (calib/nipple_interval).
    doc, _, _ = nipple_run
    unc = doc["uncertainty"]
    assert unc["method"] == "profile" and unc["residual_sd_mm"] > 0
    lo, hi = doc["c1_ci95_pa"]
    assert lo < doc["c1_pa"] < hi
    # the profile rows are the interval search's evaluations: the deviance crosses the
    # chi-square(1) 95 % quantile 3.84 on both sides (the bracket widens until an
    # evaluation reaches it, so a row at or above it stands on each side)
    from calib.fitting.uncertainty import CHI2_1_95

    c1 = np.array([row["c1_pa"] for row in doc["profile"]])
    dev = np.array([row["minus2_delta_loglik"] for row in doc["profile"]])
    assert dev[c1 < doc["c1_pa"]].max() >= CHI2_1_95 and dev[c1 > doc["c1_pa"]].max() >= CHI2_1_95


def test_error_maps_and_meshes_are_written(nipple_run):
    import meshio

    doc, _, work = nipple_run
    for rel in doc["scans"]["right_lateral"]["files"]:
        assert (work / rel).is_file(), rel
    # review CG-3: the files were only checked to exist; read back, each says what the
    # record says. The error map (what `view` colours): one signed value per vertex of
    # the scan's surface, its largest |value| the record's max (float32 in the file:
    # rel 1e-6). Every deformed state: the stress-free reference plus its displacement
    # (float64 rounding of ~100 mm: 1e-9 mm), and its displacement from the loaded reference
    # leads every scan back to one loaded reference mesh (measured 4e-15 mm; 1e-9 mm).
    ref = meshio.read(work / "calibration" / "reference_mesh.vtu")
    loaded = []
    for name, scan in doc["scans"].items():
        if name == "right_lateral":
            err = meshio.read(work / "calibration" / f"{name}_error.ply").point_data["error_mm"]
            surface = meshio.read(work / "scans" / name / "surface.ply")
            assert len(err) == len(surface.points)
            assert err.min() < 0.0 < err.max()
            top = scan["surface_error_mm"]["fiducial"]["max"]
            assert np.abs(err).max() == pytest.approx(top, rel=1e-6)
        state = work / "calibration" / f"{name}_deformed.vtu"
        if not state.is_file():  # the reference scan has no FE state
            continue
        m = meshio.read(state)
        assert np.abs(m.points - ref.points - m.point_data["displacement_mm"]).max() <= 1e-9
        loaded.append(m.points - m.point_data["displacement_from_reference_mm"])
    assert len(loaded) >= 2
    for other in loaded[1:]:
        assert np.abs(other - loaded[0]).max() <= 1e-9


def test_calibrate_ends_with_the_validation_report(nipple_run):
    doc, output, work = nipple_run
    val = json.loads((work / "validation.json").read_text())
    assert val["calibration_run_id"] == doc["run_id"] and "validation" in output
    tilt = val["scans"]["tilt_50"]
    # the posture angle comes from the registered gravity, not from session.toml: the twin
    # poses the 50 deg scan with up to 1 deg of tilt (fem.postures.random_scanner_pose,
    # uniform), registered to the scan's rotation sd (~0.02 deg): 1 deg plus 3 of those
    # (review CG-16: abs=2 had one degree unexplained)
    sd = json.loads((work / "scans" / "tilt_50" / "ingest.json").read_text())["rotation_sd_deg"]
    assert tilt["role"] == "validation"
    assert tilt["posture_angle_deg"] == pytest.approx(50, abs=1.0 + 3 * sd)
    mean = tilt["surface_error_mm"]["fiducial"]["mean"]
    # the same saved state measured twice (calibrate's evaluation, validate's re-measure)
    same = doc["scans"]["tilt_50"]["surface_error_mm"]["fiducial"]["mean"]
    assert mean["value"] == pytest.approx(same, rel=1e-9)
    lo, hi = mean["ci95"]
    assert lo <= mean["value"] <= hi and hi > lo  # a c1 interval of non-zero width moves it
    assert tilt["dissertation"]["surface_mean_mm"] == 2.69  # the 50 deg row of Table 4.1
    # the ICP frame's own fit, as calibration.json has it (review BP, P8)
    icp = doc["scans"]["tilt_50"]["icp"]
    assert tilt["icp"]["fitness"] == pytest.approx(icp["fitness"], rel=1e-9)
    assert tilt["icp"]["settled"] == icp["settled"] and 0 < icp["fitness"] <= 1
    # the landmark distance, as calibration.json has it (the same saved state)
    landmark = tilt["nipple_landmark_error_mm"]["fiducial"]
    assert landmark["value"] == pytest.approx(
        doc["scans"]["tilt_50"]["nipple_landmark_error_mm"]["fiducial"], rel=1e-9
    )
    assert landmark["ci95"][0] <= landmark["value"] <= landmark["ci95"][1]
    from calib.fitting.result import calibration_caveats

    assert val["calibration_caveats"] == calibration_caveats(doc)
    for rel in val["files"]:
        assert (work / rel).is_file(), rel
    assert "tilt_50" in (work / "validation" / "report.html").read_text()


def test_work_folder_api(nipple_run):
    import calib

    doc, _, work = nipple_run
    w = calib.load_work(work)
    assert w.c1_pa == doc["c1_pa"] and "tilt_50 (validation)" in repr(w)
    # review BW, F4: the folder's and the measurements' reprs dumped records and arrays
    assert repr(w.folder).startswith(f"WorkFolder({str(w.folder.path)!r}: c1 = ")
    assert "tilt_50 (validation)" in repr(w.folder.measurements)
    assert len(repr(w.folder)) < 300 and len(repr(w.folder.measurements)) < 300
    assert "<table>" in w._repr_html_() and "| tilt_50 |" in w.validation_table()
    for fig in (w.plot_error_map("tilt_50"), w.plot_error_by_displacement(), w.plot_profile()):
        assert fig.axes
    from calib.evaluation import EvaluationError

    # review BW, F2: a KeyError, where the README says EvaluationError
    with pytest.raises(EvaluationError, match="'left_lateral' .it is the reference scan"):
        w.plot_error_map("left_lateral")  # the reference has no simulated state
    with pytest.raises(EvaluationError, match="'tilt_99' .unknown scan"):
        w.plot_error_map("tilt_99")
    # review AI: Work == Work raised on the arrays, which a caller could overwrite
    assert w == w and w != calib.load_work(work) and w.folder == w.folder
    state = w.folder.states["tilt_50"]
    with pytest.raises(ValueError, match="read-only"):
        state.positions_mm[0, 0] = 0.0
    assert not state.tumour_mm.flags.writeable


def test_a_loaded_work_folder_refuses_changes_and_copies_edit_freely(nipple_run):
    # review BW, F3: `w.record["c1_pa"] = 1.0` made the object report c1 = 1 Pa, and
    # `w.folder.states.clear()` made it say every scan had failed
    import copy
    import dataclasses
    import pickle

    import calib

    doc, _, work = nipple_run
    w = calib.load_work(work)
    c1, n_states = w.c1_pa, len(w.folder.states)
    for change in (
        lambda: w.record.__setitem__("c1_pa", 1.0),
        lambda: w.record.update(c1_pa=1.0),
        lambda: w.record["c1_ci95_pa"].__setitem__(0, 1.0),
        lambda: w.record["scans"]["tilt_50"].pop("role"),
        lambda: w.folder.states.clear(),
        lambda: w.folder.states.__setitem__("tilt_50", None),
    ):
        with pytest.raises((TypeError, AttributeError)):
            change()
    with pytest.raises(dataclasses.FrozenInstanceError):
        w.folder = None
    assert w.c1_pa == c1 == doc["c1_pa"] and len(w.folder.states) == n_states
    # to a reader and to json it is the record; a copy is a plain one to edit
    assert w.record == doc and json.loads(json.dumps(w.record)) == doc
    edited = copy.deepcopy(w.record)
    edited["scans"]["tilt_50"]["role"] = "x"
    assert type(edited) is dict and w.record["scans"]["tilt_50"]["role"] != "x"
    again = pickle.loads(pickle.dumps(w.folder))
    assert again.record == doc and set(again.states) == set(w.folder.states)
    with pytest.raises(TypeError):
        again.record["c1_pa"] = 1.0
    # review BW, F3: a prediction's arrays were writable in its frozen dataclass
    from nn.surrogate import Prediction

    given = np.zeros((1, 2, 3))
    p = Prediction(np.zeros((1, 4, 3)), given, None, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="read-only"):
        p.surface_mm[0, 0, 0] = 99.0
    given[0, 0, 0] = 1.0  # review BZ, F9: the caller's own array stays as it was given


def test_calib_validate_of_a_loaded_work_keeps_its_figures(
    nipple_run, tmp_path, monkeypatch, caplog
):
    # review BW, F8: notebook 02 validated, then its table computed the validation again
    import shutil

    import calib
    import calib.notebook

    _, _, work = nipple_run
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    w = calib.load_work(copy)
    record = calib.validate(w)
    assert record["calibration_run_id"] == w.record["run_id"]

    def again(*args):
        raise AssertionError("the validation was computed again")

    monkeypatch.setattr(calib.notebook, "validate_work", again)
    table = w.validation_table()
    mean_mm = record["scans"]["tilt_50"]["surface_error_mm"]["fiducial"]["mean"]["value"]
    assert "| tilt_50 |" in table and f"{mean_mm:.2f}" in table
    # a work folder calibrated again since it was loaded: the report is the new one's,
    # the loaded object keeps (and computes from) its own states (review BZ, F7: this
    # part called keep_validation alone, and its last check could not fail)
    import logging

    old = calib.load_work(copy)
    rec = json.loads((copy / "calibration.json").read_text())
    (copy / "calibration.json").write_text(json.dumps(rec | {"run_id": "forged"}))
    run = json.loads((copy / "calibration" / "RUN").read_text())
    (copy / "calibration" / "RUN").write_text(json.dumps(run | {"run_id": "forged"}))
    monkeypatch.undo()  # the new calibration's validation is computed
    with caplog.at_level(logging.WARNING, logger="calib.api"):
        again = calib.validate(old)
    assert again["calibration_run_id"] == "forged" and old._validation is None
    assert "was calibrated again since it was loaded" in caplog.text
    # the other entry points take a loaded folder as its path (review BZ, F6: they
    # failed with "expected str, bytes or os.PathLike object")
    import calib.workflows.diagnose
    import calib.workflows.sweep

    seen = []
    monkeypatch.setattr(
        calib.workflows.diagnose, "run_diagnosis", lambda p, *a, **k: seen.append(p)
    )
    monkeypatch.setattr(calib.workflows.sweep, "run_sweep", lambda p, *a, **k: seen.append(p))
    calib.diagnose(w)
    calib.gravity_sweep(w.folder, tmp_path / "sweep.zarr")
    assert seen == [w.folder.path, w.folder.path]


def test_a_work_folder_s_options_are_named_as_python_calls_them(tmp_path):
    # review BZ, F4: calibrate and ingest take `work`, and were told of `out (--out)`
    import calib

    (tmp_path / "afile").write_text("")
    for call in (calib.ingest, calib.calibrate):
        with pytest.raises(NotADirectoryError, match=r"^work \(--out\) .*afile: exists and is not"):
            call(tmp_path / "scans", tmp_path / "afile")


def test_the_profile_of_a_joint_refit_is_drawn_without_its_evaluations(nipple_run, tmp_path):
    # review CB: a diagnosis refit's history holds parameter vectors and sums of squares,
    # and plot_profile raised KeyError 'c1_pa' on the folder diagnose says load_work takes
    import shutil

    import calib

    _, _, work = nipple_run
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    rec = json.loads((copy / "calibration.json").read_text())
    rec |= {"history": [{"x": [6.0, 1.5], "sum_sq_mm2": 2.0}], "profile": []}
    (copy / "calibration.json").write_text(json.dumps(rec))
    fig = calib.load_work(copy).plot_profile()
    assert "a joint fit" in fig.axes[0].get_title()
    assert not calib.load_work(work).plot_profile().axes[0].get_title()


def test_work_figures_show_as_images_in_an_ipython_kernel(nipple_run):
    # review AG: a bare matplotlib Figure (no pyplot) showed as its text in Jupyter until
    # %matplotlib inline had run; load_work registers a PNG formatter in a running shell
    from IPython.core.interactiveshell import InteractiveShell

    import calib

    _, _, work = nipple_run
    shell = InteractiveShell.instance()
    try:
        fig = calib.load_work(work).plot_profile()
        data, _ = shell.display_formatter.format(fig)
        assert data["image/png"].startswith(b"\x89PNG")
        # a formatter the user's shell has already (inline, retina) is left as it is
        from matplotlib.figure import Figure

        mine = lambda fig: b"mine"  # noqa: E731
        png = shell.display_formatter.formatters["image/png"]
        png.for_type(Figure, mine)
        calib.load_work(work)
        assert png.lookup_by_type(Figure) is mine
    finally:
        InteractiveShell.clear_instance()


def test_a_scan_without_fe_solution_is_listed_not_dropped_by_validate(nipple_run, tmp_path):
    # calibrate writes `failed` for a scan with no FE solution at the calibrated c1 and
    # saves no state for it; validate listed the other scans only, without a word
    import shutil

    _, _, work = nipple_run
    assert json.loads((work / "validation.json").read_text())["failed"] == {}
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    rec = json.loads((copy / "calibration.json").read_text())
    tilt = rec["scans"]["tilt_50"]
    why = "load not applied: no step of the load converged (test)"
    rec["scans"]["tilt_50"] = {k: tilt[k] for k in ("role", "gravity_ref")} | {"failed": why}
    (copy / "calibration.json").write_text(json.dumps(rec))
    res = CliRunner().invoke(app, ["validate", str(copy)])
    assert res.exit_code == 0, res.output
    val = json.loads((copy / "validation.json").read_text())
    assert "tilt_50" not in val["scans"] and val["failed"] == {"tilt_50": why}
    assert "tilt_50" in res.output and "not validated" in res.output
    assert (
        f"Not validated: tilt_50, no FE solution at calibration ({why})"
        in (copy / "validation" / "report.html").read_text()
    )


def test_validate_says_where_the_session_says_its_scans_were_simulated(nipple_run, tmp_path):
    # review BY, F13: the twin's 0.15 mm stood beside the dissertation's MRI 3.63 mm in
    # the report without a word that the scans were simulated
    import shutil

    doc, output, work = nipple_run
    source = doc["scans_source"]
    assert source["simulated"] is True and "synth, preset custom" in source["generator"]
    said = "the scans were simulated (session.toml [source]: phantom-calib"
    assert json.loads((work / "validation.json").read_text())["scans_source"] == source
    assert said in (work / "validation" / "report.html").read_text()
    assert f"WARNING: {said}" in " ".join(output.split())  # calibrate's closing validate
    # a session that does not say: nothing said (the independent generator's, a scanner's)
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    rec = json.loads((copy / "calibration.json").read_text())
    (copy / "calibration.json").write_text(json.dumps(rec | {"scans_source": None}))
    res = CliRunner().invoke(app, ["validate", str(copy)])
    assert res.exit_code == 0, res.output
    assert "scans were simulated" not in res.output
    assert "scans were simulated" not in (copy / "validation" / "report.html").read_text()


def test_a_band_is_the_figure_s_range_over_the_whole_interval(nipple_run):
    # review AJ: the band was the figure at the interval's two ends and the estimate; a
    # distance smallest inside the interval had a band that missed it. The tumour centre's
    # fiducial error |t + dt u - m| over u in the interval has a closed-form range.
    from calib.data.work import read_work
    from calib.validation import BAND_POINTS

    doc, _, work = nipple_run
    val = json.loads((work / "validation.json").read_text())
    measured = read_work(work).measurements.scans
    lo_u, hi_u = np.log(np.asarray(doc["c1_ci95_pa"]) / doc["c1_pa"])
    step = (hi_u - lo_u) / (BAND_POINTS - 1)
    inside = []  # scans whose tumour error is smallest well inside the interval
    for name, s in val["scans"].items():
        model = doc["scans"][name]["model"]
        t, dt = np.asarray(model["tumour_mm"]), np.asarray(model["dtumour_dlnc1_mm"])
        e0 = t - measured[name].tumour_mm
        u_free = -(e0 @ dt) / (dt @ dt)
        inside.append(lo_u + step < u_free < hi_u - step and abs(u_free) > step)
        u_star = np.clip(u_free, lo_u, hi_u)  # the nearest point on the segment
        ends = [np.linalg.norm(e0 + u * dt) for u in (lo_u, hi_u)]
        low, high = np.linalg.norm(e0 + u_star * dt), max(ends)
        # the grid's step (BAND_POINTS - 1 steps) is at most half a step from u_star, and
        # the distance changes by at most |dt| per unit of u (its Lipschitz constant)
        band = s["tumour_error_mm"]["fiducial"]["ci95"]
        # (1e-9 mm: round-off of the two ways of computing one distance)
        assert low - 1e-9 <= band[0] <= low + np.linalg.norm(dt) * step / 2 + 1e-9, name
        assert band[1] == pytest.approx(high, rel=1e-9), name
    # review AK: the check tells the grid from the ends and the estimate only where a
    # minimum lies inside, away from both (on this fixture the right lateral's)
    assert any(inside), inside


def test_a_work_folder_ingested_again_after_its_calibration_is_refused(nipple_run, tmp_path):
    # review AI: a new ingest into a calibrated WORK was read with the old fit's saved
    # states, and validate wrote errors 4-8 times the fitted scans' without a word
    import shutil

    from calib.data.work import read_work
    from calib.io import StaleOutputError, run_id_of, write_json_atomic

    doc, _, work = nipple_run
    assert doc["ingest_run_id"] == run_id_of(work / "scans") is not None
    assert read_work(work).measurements.density_kg_m3 == doc["model"]["density_kg_m3"]
    with pytest.raises(FileNotFoundError, match="is a file: pass the work folder"):
        read_work(work / "calibration.json")  # it said "no calibration.json"
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    write_json_atomic(copy / "scans" / "RUN", {"run_id": "a-later-ingest"})
    with pytest.raises(StaleOutputError, match="ingested again after this calibration"):
        read_work(copy)
    before = (copy / "validation.json").read_text()
    res = CliRunner().invoke(app, ["validate", str(copy)])
    assert res.exit_code == 2 and "run `phantom-calib calibrate` again" in res.output
    assert (copy / "validation.json").read_text() == before  # nothing written


def test_simulate_on_the_calibrated_mesh_gives_calibrate_s_own_state(nipple_run, tmp_path, caplog):
    # make demo's last step: simulate on calibrate's stress-free reference_mesh.vtu at
    # the calibrated c1 and a scan's gravity_ref. Review AT: the back plane simulate
    # detected clamped 3 nodes the calibration left free (0.59 mm off its state); with
    # the mesh's own set:back the two code paths solve one problem. Tolerance: both
    # Newton solves stop at rtol 1e-8 of the load, each at its own last iterate: measured
    # 5.4e-8 mm apart; the bar 1e-6 mm leaves a factor 20 (review CG-15: the comment said
    # ~1e-9 mm)
    import meshio

    doc, _, work = nipple_run
    assert doc["reference_recovery"]["method"] in ("newton", "fixed-point")  # straight
    name = next(n for n, s in doc["scans"].items() if s["role"] == "calibration")
    gravity = ",".join(map(str, doc["scans"][name]["gravity_ref"]))
    out = tmp_path / "sim.vtu"
    res = CliRunner().invoke(app, ["simulate", str(work / "calibration" / "reference_mesh.vtu"),
                                   "--c1", str(doc["c1_pa"]), f"--gravity={gravity}",
                                   "--out", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    u = meshio.read(out).point_data["displacement_mm"]
    state = meshio.read(work / "calibration" / f"{name}_deformed.vtu")
    assert np.linalg.norm(state.point_data["displacement_mm"], axis=1).max() > 5.0
    assert np.abs(u - state.point_data["displacement_mm"]).max() < 1e-6
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["back"]["source"] == "set:back"
    # review BP: the calibration's record beside its mesh is read; the same model, no word
    assert result["calibration"] == {
        "path": str((work / "calibration.json").resolve()), "differences": {}, "reference": None
    }  # fmt: skip
    assert (result["nipple_source"], result["nipple_node"]) == (
        "set:nipple",
        doc["model"]["nipple_node"],
    )
    # review BP, P1: another density (a phantom of 1200 kg/m^3 solved at the default 1000
    # moved 17 % less than its calibrated model, silently) is said, with the option to give
    other = tmp_path / "other.vtu"
    with caplog.at_level("WARNING"):
        res = CliRunner().invoke(app, ["simulate", str(work / "calibration" / "reference_mesh.vtu"),
                                       "--c1", str(doc["c1_pa"]), f"--gravity={gravity}",
                                       "--density", "1200", "--out", str(other)])  # fmt: skip
    assert res.exit_code == 0, res.output
    said = "this solve is not the calibrated model's: --density 1200.0 (calibrated: 1000.0)"
    assert said in caplog.text and "(for the calibrated model: --density 1000.0)" in caplog.text
    differences = json.loads(other.with_suffix(".json").read_text())["calibration"]["differences"]
    assert differences == {"--density": [1000.0, 1200.0]}


def test_hand_edited_arrays_of_a_work_folder_are_named(nipple_run, tmp_path):
    # review AT: an ingest.json nipple of null was an IndexError traceback, a deformed
    # mesh without its displacement a bare KeyError 'displacement_mm'
    import shutil

    import meshio

    from calib.data.work import read_work

    doc, _, work = nipple_run
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    name = next(iter(doc["scans"]))
    ingest = copy / "scans" / name / "ingest.json"
    kept = ingest.read_text()
    edited = json.loads(kept)
    edited["nipple_lps_mm"] = None
    ingest.write_text(json.dumps(edited))
    with pytest.raises(ValueError, match=rf"{name}/ingest.json: `nipple_lps_mm` must be 3 finite"):
        read_work(copy)
    ingest.write_text(kept)
    deformed = copy / "calibration" / f"{name}_deformed.vtu"
    m = meshio.read(deformed)
    meshio.write(deformed, meshio.Mesh(m.points, m.cells))
    with pytest.raises(ValueError, match=rf"{name}_deformed.vtu: no `displacement_mm` point"):
        read_work(copy)


def test_an_older_record_is_checked_by_its_ingest_hashes(nipple_run, tmp_path):
    # review AN: a record without ingest_run_id (written before it) was read with any
    # scans: another phantom's ingest gave 19 mm errors at exit status 0
    import json
    import shutil

    from calib.data.work import read_work
    from calib.io import StaleOutputError

    _, _, work = nipple_run
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    record = json.loads((copy / "calibration.json").read_text())
    del record["ingest_run_id"]
    (copy / "calibration.json").write_text(json.dumps(record))
    read_work(copy)  # its scans as it fitted them: read
    ingest = copy / "scans" / "tilt_50" / "ingest.json"
    ingest.write_text(ingest.read_text().replace("{", '{"edited": 1, ', 1))
    with pytest.raises(StaleOutputError, match=r"tilt_50/ingest.json: not the file this"):
        read_work(copy)


def test_a_command_on_a_work_folder_in_use_is_refused(nipple_run, tmp_path):
    # review AN: an ingest during a calibration, and a validate beside one, wrote into the
    # same WORK: a record naming scans it never fitted, an old fit's validation
    import shutil
    import subprocess
    import sys

    _, _, work = nipple_run
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    before = (copy / "validation.json").read_text()
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom calib.io import work_lock\n"
         "with work_lock(sys.argv[1], 'calibrate'):\n print('held', flush=True)\n"
         " time.sleep(60)", str(copy)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        res = CliRunner().invoke(app, ["validate", str(copy)])
        assert res.exit_code == 2, res.output
        assert "in use by another phantom-calib command (calibrate, process" in res.output
        assert (copy / "validation.json").read_text() == before  # nothing written
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    res = CliRunner().invoke(app, ["validate", str(copy)])  # released with its process
    assert res.exit_code == 0, res.output


def test_validate_and_diagnose_take_the_work_folder_a_notebook_holds(nipple_run):
    # review AI: calib.load_work's object and a path raised AttributeError in both
    import calib
    from calib.data.work import WorkFolder, as_work_folder
    from calib.validation import validate_work

    _, _, work = nipple_run
    held = calib.load_work(work)
    assert as_work_folder(held) is held.folder
    assert isinstance(as_work_folder(str(work)), WorkFolder)
    with pytest.raises(TypeError, match="expected a work folder: its path"):
        as_work_folder(3)
    assert validate_work(held, scans="tilt_50").scans["tilt_50"].role == "validation"
    with pytest.raises(ValueError, match="no scan named"):  # it meant every scan
        validate_work(held, scans=[])
    # review AU: a notebook's wrong arguments ended in matplotlib's or numpy's words
    with pytest.raises(ValueError, match="vmax must be a positive number of mm"):
        held.plot_error_map("tilt_50", vmax=-1)
    with pytest.raises(TypeError, match="scans must be a scan name or names, got 3"):
        held.plot_error_by_displacement(3)
    with pytest.raises(TypeError, match="evaluate takes the Calibration that calib.fit returns"):
        calib.evaluate(held)
    with pytest.raises(TypeError, match="check_postures takes the Calibration"):
        calib.check_postures(str(work), {})
    with pytest.raises(TypeError, match="fit takes the Measurements of calib.load_measurements"):
        calib.fit(str(work))
    # review AT: every scan marked failed gave an empty report, exit 0
    import dataclasses

    record = dict(held.folder.record)
    record["scans"] = {
        n: s | {"failed": "no FE solution (test)"} for n, s in record["scans"].items()
    }
    none = dataclasses.replace(held.folder, states={}, record=record)
    with pytest.raises(ValueError, match="no scan to validate: every scan in calibration.json"):
        validate_work(none)


def test_a_tumour_without_its_c1_derivative_gets_no_band(nipple_run, tmp_path):
    # the band of a figure is its range over the c1 interval; a tumour whose derivative
    # was not saved does not move with c1 and got the zero-width band [v, v]
    import shutil

    _, _, work = nipple_run
    before = json.loads((work / "validation.json").read_text())["scans"]["tilt_50"]
    lo, hi = before["tumour_error_mm"]["fiducial"]["ci95"]
    assert hi > lo
    copy = tmp_path / "work"
    shutil.copytree(work, copy)
    rec = json.loads((copy / "calibration.json").read_text())
    rec["scans"]["tilt_50"]["model"]["dtumour_dlnc1_mm"] = None
    (copy / "calibration.json").write_text(json.dumps(rec))
    res = CliRunner().invoke(app, ["validate", str(copy)])
    assert res.exit_code == 0, res.output
    tilt = json.loads((copy / "validation.json").read_text())["scans"]["tilt_50"]
    tumour = tilt["tumour_error_mm"]["fiducial"]
    assert tumour["ci95"] is None
    assert tumour["value"] == before["tumour_error_mm"]["fiducial"]["value"]
    assert tilt["nipple_error_mm"]["fiducial"]["ci95"] is not None


def test_unrecoverable_reference_stops_early_with_remedies(twin_scans, tmp_path, monkeypatch):
    # An explicit --mesh-size is not retried; the error names the scan, the mesh and what
    # to change, before any optimisation.
    real = calib.model.forward.ForwardModel.stress_free

    def no_reference(self, theta):
        if self.reference_state == "unload":
            raise fem.ConvergenceError("inverse Newton stopped at load factor 0.8 (test)")
        return real(self, theta)

    monkeypatch.setattr(calib.model.forward.ForwardModel, "stress_free", no_reference)
    res = CliRunner().invoke(app, ["calibrate", str(twin_scans), "--out", str(tmp_path / "w"),
                                   "--mesh-size", "14"])  # fmt: skip
    assert res.exit_code != 0
    for part in ("'left_lateral'", "14 mm model mesh", "--mesh-size", "--reference-state shortcut"):
        assert part in res.output, res.output
    assert not (tmp_path / "w" / "calibration.json").exists()


def _failing_calibrator(fail_below_pa: float):
    """A stand-in calibrator whose FE fails below a c1 (the shortcut's 2 g flip does)."""
    from types import SimpleNamespace

    def residuals(theta, scans, *, gradient, retry=True):
        calls.append(retry)
        if np.exp(theta) < fail_below_pa:
            raise fem.ConvergenceError("load not applied (test)")
        return {"s": SimpleNamespace(r=np.array([np.exp(theta) - 500.0]))}

    def evaluate(theta, gravities, *, gradient):
        residuals(theta, None, gradient=gradient)
        raise AssertionError("only the failing branch is exercised here")

    calls: list[bool] = []
    return SimpleNamespace(options=SimpleNamespace(profile_points=5), calibration_scans=[],
                           residuals=residuals, fm=SimpleNamespace(evaluate=evaluate),
                           retries=calls)  # fmt: skip


def test_failed_profile_point_is_recorded_not_fatal():
    # Found on the skin twin with --reference-state shortcut: a profile point below the
    # calibrated c1 failed and the whole (finished) calibration was lost.
    cal = _failing_calibrator(480.0)
    rows = calib.fitting.profile.likelihood_profile(cal, np.log(500.0), 0.05, 10.0)
    assert cal.retries == [False] * 5  # a profile point is not worth the slow retry
    failed = [r for r in rows if r.get("failed")]
    assert failed and all(r["c1_pa"] < 480.0 and r["objective"] is None for r in failed)
    ok = [r for r in rows if not r.get("failed")]
    assert len(ok) == 5 - len(failed) and min(r["minus2_delta_loglik"] for r in ok) == 0.0
    # a line per point (review AX: a minute of FE solves passed without a word)
    said = []
    calib.fitting.profile.likelihood_profile(cal, np.log(500.0), 0.05, 10.0, say=said.append)
    assert len(said) == 5 and said[0].startswith("  profile point 1/5: c1 = 452.4 Pa, no FE")
    assert "objective" in said[-1]


def test_scan_without_solution_at_the_calibrated_c1_is_reported():
    from types import SimpleNamespace

    from calib.evaluation import evaluate

    posture = {"plane": "transverse", "angle_deg": 50.0}
    g = np.array([0.0, 0, 1])
    scan = SimpleNamespace(name="tilt", role="validation", gravity_ref=g, nominal_posture=posture)
    cal = _failing_calibrator(1e9)
    cal.mesh = SimpleNamespace(node_set=lambda name: np.array([0]))
    cal.measurements = SimpleNamespace(scans={"tilt": scan})
    calibration = SimpleNamespace(calibrator=cal, theta=float(np.log(500.0)))
    out = evaluate(calibration, scans=["tilt"])["tilt"]
    assert out.failed is not None and "load not applied" in out.failed
    assert out.to_json() == {"role": "validation", "gravity_ref": [0.0, 0.0, 1.0],
                             "posture": posture, "failed": out.failed}  # fmt: skip


def test_the_posture_test_s_verdict_says_what_it_leaves_out():
    # review AX: on a homogeneous quick twin (14 mm) calibrate said "the model misses an
    # effect that changes with posture" and diagnose "no missing effect", unreconciled
    from types import SimpleNamespace

    from calib.workflows.calibrate import _posture_line

    est = [SimpleNamespace(label=0, theta=np.log(424.4)), SimpleNamespace(label=1, theta=6.07)]
    test = SimpleNamespace(verdict="inconsistent", estimates=est, p_value=0.0014, alpha=0.04)
    line = _posture_line(test, {0: "right_lateral", 1: "tilt_50"})
    assert line.startswith("POSTURE INCONSISTENCY: the scans alone ask for different c1 ")
    assert "right_lateral 424 Pa, tilt_50 433 Pa; Cochran Q p = 0.0014 < 0.04" in line
    assert "leaves the model mesh's discretisation out" in line and "diagnose" in line
