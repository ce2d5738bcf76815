"""What calibration.json says a reader of figures made from it must be told (and how an
ingest result prints).

Review AJ: `validate`, its reports and the notebook's `Work` printed "95 % bands" from a
calibration whose record said `misfit` (or an optimiser that did not converge) without a
word. The caveats are read from the record alone, so the checks are exact.
"""

from __future__ import annotations

import numpy as np
import pytest

from calib.fitting.result import calibration_caveats
from calib.report.tables import format_validation

CLEAN = {
    "objective": "surface",
    "model_fit": {"verdict": "fits"},
    "optimiser": {"success": True, "bound": None, "message": "converged"},
    "uncertainty": {"method": "series"},
}


def test_a_clean_calibration_has_no_caveat():
    assert calibration_caveats(CLEAN) == []
    # the nipple objective has no model-fit test and a profile interval: nothing to say
    assert calibration_caveats({"objective": "nipple", "model_fit": None}) == []


def test_each_caveat_is_said_once():
    record = CLEAN | {
        "model_fit": {"verdict": "misfit"},
        "optimiser": {"success": False, "bound": "upper", "message": "no decrease found"},
        "uncertainty": {"method": "gauss-newton"},
    }
    said = calibration_caveats(record)
    assert len(said) == 4
    assert said[0].startswith("model misfit") and "effective c1" in said[0]
    assert said[1] == "the optimiser did not converge (no decrease found)"
    assert said[2] == "c1 ended on the upper bound of its search range"
    assert "Gauss-Newton" in said[3]
    # a refit's optimiser names its bound "theta" (review AK: "the theta bound")
    theta = record | {"optimiser": {"success": True, "bound": "theta"}}
    assert "c1 ended on a bound of its search range" in calibration_caveats(theta)
    # the landmarks objective's interval is the Gauss-Newton one by design
    assert calibration_caveats(record | {"objective": "landmarks"})[-1].startswith("c1 ended")
    # review AO: on a retry mesh (16 mm after 12 and 14 failed) an independent generator's
    # c1 fell outside its interval
    retry = CLEAN | {
        "mesh": {"size_mm": 16.0, "failed_sizes": [{"mesh_size_mm": 12.0}, {"mesh_size_mm": 14.0}]}
    }
    (said,) = calibration_caveats(retry)
    assert said.startswith("calibrated on the 16 mm retry mesh (no FE solution on 12, 14 mm)")
    assert calibration_caveats(CLEAN | {"mesh": {"size_mm": 12.0, "failed_sizes": []}}) == []


def test_a_body_few_elements_tall_is_a_caveat():
    # review BN: a body half the twins' size gets 3 elements of the default 12 mm through
    # its height, and the check meshes are coarser still; said in the log only
    few = CLEAN | {"mesh": {"size_mm": 12.0, "height_mm": 37.3, "elements_in_height": 3.1}}
    (said,) = calibration_caveats(few)
    assert said.startswith("the model mesh has 3.1 elements of 12 mm through the body's 37 mm")
    assert "--mesh-size of about 6 mm" in said
    twin = CLEAN | {"mesh": {"size_mm": 12.0, "height_mm": 74.5, "elements_in_height": 6.2}}
    assert calibration_caveats(twin) == []


def test_a_repaired_reference_surface_is_a_caveat():
    # review BN: clamped within size/5 (2.4 mm at 12 mm), the rim's wall with it
    support = {"surface": "repaired", "back_tol_mm": 2.4, "clamped_mm2": 7461.0}
    (said,) = calibration_caveats(CLEAN | {"mesh": {"size_mm": 12.0, "support": support}})
    assert "after TetGen's repair" in said and "within 2.4 mm of the plate" in said
    for surface in ("decimated", "remeshed"):
        kept = CLEAN | {"mesh": {"size_mm": 12.0, "support": support | {"surface": surface}}}
        assert calibration_caveats(kept) == []


def test_a_mesh_check_that_failed_is_a_caveat_and_a_warning():
    # review BN: the interval was then the noise's alone (5-10 times narrower than with a
    # discretisation bound) and only a failure string deep in the record said so
    from calib.report.tables import _uncertainty_lines

    failed = {
        "mesh_size_mm": 12.0,
        "gci_ln_c1": None,
        "convergence": "assumed order",
        "meshes": [{"mesh_size_mm": 16.8, "c1_pa": None, "failure": "ConvergenceError: x"}],
    }
    unc = {"method": "series", "c1_ci95_pa": [411.9, 415.1], "mesh_check": failed}
    (said,) = calibration_caveats(CLEAN | {"uncertainty": unc})
    assert said.startswith("no mesh check solved") and "noise only" in said
    assert any(
        line.startswith("  WARNING: no mesh check solved")
        for line in _uncertainty_lines(unc, "surface")
    )
    solved = failed | {"gci_ln_c1": 0.02}
    solved["meshes"] = [{"mesh_size_mm": 16.8, "c1_pa": 418.0, "failure": None}]
    assert calibration_caveats(CLEAN | {"uncertainty": unc | {"mesh_check": solved}}) == []
    assert not any(
        "WARNING" in x for x in _uncertainty_lines(unc | {"mesh_check": solved}, "surface")
    )


def test_the_validation_table_warns_with_each_caveat():
    doc = {"scans": {}, "calibration_caveats": ["model misfit (x)", "c1 ended on a bound"]}
    lines = format_validation(doc).splitlines()
    assert lines[1:] == [
        "WARNING (calibration): model misfit (x)",
        "WARNING (calibration): c1 ended on a bound",
    ]
    assert "WARNING" not in format_validation({"scans": {}})  # a validation.json before it


def test_an_ingest_result_prints_in_a_line_and_shows_its_table_in_jupyter():
    # review AI: the generated repr ran to 30,000 characters (every scan's arrays)
    from pathlib import Path
    from types import SimpleNamespace

    from calib.data.ingest import IngestResult

    res = IngestResult(SimpleNamespace(folder=Path("scans")), {"a": 1, "b": 2}, {}, {}, "T <x>")
    assert repr(res) == "IngestResult('scans', 2 scans)"
    assert res._repr_html_() == "<pre>IngestResult(&#x27;scans&#x27;, 2 scans)\n\nT &lt;x&gt;</pre>"


def test_a_work_folder_says_its_caveats_and_a_refit_s_effects_in_its_repr():
    from pathlib import Path
    from types import SimpleNamespace

    from calib.notebook import Work

    scans = {"ref": SimpleNamespace(role="reference")}
    record = CLEAN | {"c1_ci95_pa": None, "model": {"effects": {"named": ["skin"]}}}
    folder = SimpleNamespace(
        path=Path("w"), record=record, c1_pa=420.4, measurements=SimpleNamespace(scans=scans)
    )
    assert (
        repr(Work(folder))
        == "Work('w': c1 = 420.4 Pa with skin (diagnose's refit); ref (reference))"
    )
    folder.record = record | {"model": {}, "model_fit": {"verdict": "misfit"}}
    assert repr(Work(folder)).endswith(
        f"ref (reference); WARNING: {calibration_caveats(folder.record)[0]})"
    )


def test_calib_validate_warns_of_each_caveat_in_a_notebook(monkeypatch, caplog):
    # review AL: the command prints them in its table; calib.validate() said nothing
    import calib
    import calib.workflows.validate as workflow

    record = {"calibration_caveats": ["model misfit (x)"]}
    monkeypatch.setattr(workflow, "run_validation", lambda work, progress: record)
    with caplog.at_level("WARNING"):
        assert calib.validate("w") is record
    assert "calibration: model misfit (x)" in caplog.text


def test_a_validation_without_a_validation_scan_says_its_figures_are_fits():
    # review BP, P5: a session of a reference and calibration scans only got a
    # "Validation" table of the scans c1 was fitted to, exit 0, and nothing said so
    from types import SimpleNamespace

    from calib.report.validation import _intro
    from calib.validation import NO_VALIDATION_SCAN, Validation

    fig = {"value": 0.3, "ci95": [0.29, 0.31]}
    scan = {"role": "calibration", "posture_angle_deg": 180.0, "posture_plane": "transverse",
            "surface_error_mm": {"fiducial": {"mean": fig, "sd": fig}},
            "nipple_error_mm": {"fiducial": fig}, "tumour_error_mm": None}  # fmt: skip
    fitted = {"scans": {"right": scan, "tilt": scan}}
    assert f"WARNING: {NO_VALIDATION_SCAN}" in format_validation(fitted).splitlines()
    held = {"scans": {"right": scan, "tilt": scan | {"role": "validation"}}}
    assert "WARNING" not in format_validation(held)
    assert "WARNING" not in format_validation({"scans": {}})  # nothing to say of no scan
    # the HTML and Markdown report's introduction too
    roles = [SimpleNamespace(role="calibration")]
    v = Validation(c1_pa=420.0, c1_ci95_pa=None, scans={"right": roles[0]})
    assert v.notes == (NO_VALIDATION_SCAN,) and NO_VALIDATION_SCAN in "\n".join(_intro(v)[0])
    v = Validation(c1_pa=420.0, c1_ci95_pa=None, scans={"tilt": SimpleNamespace(role="validation")})
    assert v.notes == () and NO_VALIDATION_SCAN not in str(_intro(v))


def test_the_validation_page_s_introduction_is_a_list_and_its_columns_say_their_frame():
    # review BY, F14: the introduction was one ~1,100-character paragraph of nested
    # parentheses, and "median", "p95", "max" did not say they were the fiducial frame's
    from calib.report.validation import HEADER, _intro_markdown, validation_html
    from calib.validation import Validation

    source = {"simulated": True, "generator": "g"}
    v = Validation(c1_pa=420.0, c1_ci95_pa=(410.0, 430.0), scans={}, caveats=("misfit",),
                   scans_source=source)  # fmt: skip
    md = _intro_markdown(v)
    assert md[0] == "**WARNING (calibration): misfit.**"
    assert md[1].startswith("**WARNING: the scans were simulated (session.toml [source]: g)")
    bullets = [line for line in md if line.startswith("- ")]
    assert len(bullets) >= 8 and all(len(line) < 260 for line in md)
    assert any(line.startswith("- Fiducial frame:") for line in bullets)
    assert {"median (fiducial)", "p95 (fiducial)", "max (fiducial)"} <= set(HEADER)
    page = validation_html(v)
    assert page.count("<li>") == len(bullets) and "<strong>WARNING: the scans" in page


def test_a_posture_angle_is_said_on_its_nominal_angle_s_branch():
    # review BP, P7: an independent generator's right lateral, 0.5 deg off, read -179 deg;
    # a nominal angle written -335 (the contract allows -360...360) got no dissertation
    # figures where 25 got them
    from types import SimpleNamespace

    from calib.validation import _posture, _reference_figures

    work = SimpleNamespace(record={"model": {"R_ref_from_phantom": np.eye(3).tolist()}})

    def scan(angle_deg, nominal, role="validation"):
        a = np.radians(angle_deg)
        return SimpleNamespace(gravity_ref=np.array([np.cos(a), 0.0, np.sin(a)]), role=role,
                               posture_plane="transverse", posture_angle_deg=nominal)  # fmt: skip

    # on the nominal angle's branch, the measured angle itself (review CG-5: "within 1 deg of
    # 180" passed an implementation returning the nominal angle)
    for measured, said in ((179.2, 179.2), (-179.2, 180.8), (180.8, 180.8)):
        angle, plane = _posture(work, scan(measured, 180.0))
        assert angle == pytest.approx(said, abs=1e-9) and plane == "transverse", (measured, angle)
    assert _posture(work, scan(0.3, 0.0))[0] == pytest.approx(0.3)
    assert _posture(work, scan(-0.3, 0.0))[0] == pytest.approx(-0.3)  # not 359.7
    # no nominal angle: in (-179.5, 180.5] as before
    assert _posture(work, scan(-179.8, None))[0] == pytest.approx(180.2)
    for nominal in (25.0, -335.0):
        s = scan(25.0, nominal)
        figures = _reference_figures(s, _posture(work, s)[0], "transverse", tumour=True)
        assert figures is not None and figures["posture_angle_deg"] == 25, nominal
        assert figures["tumour_mm"] == 3.647
        # review BP, P8: no dissertation tumour figure beside a phantom without a tumour
        bare = _reference_figures(s, _posture(work, s)[0], "transverse", tumour=False)
        assert "tumour_mm" not in bare and bare["surface_mean_mm"] == 3.63


def test_the_validation_table_prints_the_icp_fitness():
    # review BP, P8: the ICP frame's figures travelled without the ICP's own fit
    from calib.report.validation import HEADER, _icp_fit

    assert "ICP fitness" in HEADER
    assert _icp_fit({"fitness": 0.9942, "settled": True}) == "0.99"
    assert _icp_fit({"fitness": 0.41, "settled": False}) == "0.41 (not settled)"
    assert _icp_fit({}) == "–"
