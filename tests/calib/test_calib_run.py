"""``phantom-calib calibrate`` end to end on a small twin: the public output contract.

The twin (two lateral postures, 14 mm phantom, 2 mm voxels) keeps this in the default
suite; the accuracy of the calibration is tested on FE-made measurements in
test_calib_calibrate.py and measured on the full presets by benchmarks/bench_calib.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from calib_helpers import SMALL_PRESET
from typer.testing import CliRunner

from calib.cli import app
from calib.twin import synthesize


@pytest.fixture(scope="module")
def twin_scans(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "twin"
    synthesize(out, preset=SMALL_PRESET, seed=3)
    return out / "scans"


def _calibrate(scans, work, *args):
    res = CliRunner().invoke(app, ["calibrate", str(scans), "--out", str(work), "--mesh-size",
                                   "14", *args])  # fmt: skip
    assert res.exit_code == 0, res.output
    return json.loads((work / "calibration.json").read_text()), res.output, work


@pytest.fixture(scope="module")
def nipple_run(twin_scans, tmp_path_factory):
    return _calibrate(twin_scans, tmp_path_factory.mktemp("work"), "--objective", "nipple")


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
    # chi-square(1) 95 % quantile 3.84 on both sides
    c1 = np.array([row["c1_pa"] for row in doc["profile"]])
    dev = np.array([row["minus2_delta_loglik"] for row in doc["profile"]])
    assert dev[c1 < doc["c1_pa"]].max() > 3.5 and dev[c1 > doc["c1_pa"]].max() > 3.5


def test_error_maps_and_meshes_are_written(nipple_run):
    doc, _, work = nipple_run
    for rel in doc["scans"]["right_lateral"]["files"]:
        assert (work / rel).is_file(), rel
    assert (work / "calibration" / "reference_mesh.vtu").is_file()
