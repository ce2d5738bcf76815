"""The missing-effect diagnosis on digital twins: recovery of a hidden truth (slow).

Tiny four-posture twins (14 mm phantom, 10 mm truth mesh, 2 mm voxels: the dissertation's
postures) calibrated on a 14 mm model mesh, then diagnosed with the defaults (fitted:
right lateral and 50 deg; held out: 25 deg):

- the preset's hidden skin (1.5 mm, 8x) is named ``skin`` and the refit brings c1 back
  towards the truth; the refitted model is a work folder ``validate`` accepts;
- a homogeneous truth (``--effect none``) gives ``no missing effect``;
- an effect outside the library, built here for the test only (a local pad pressing on
  the flank in the 50 deg posture: point loads added to that posture's truth solve), is
  ``unexplained``;
- the noise model, measured from the residuals, against the twin's known imaging error;
- on the homogeneous twin, the skin's detectable size in its own ratio lies under the x8
  the skin twin names.
- with the model mesh's own error absorbed (``--mesh-error absorbed``) the skin is still
  named and the homogeneous truth gets no name.

Each twin costs about 1 min to build and calibrate and 2-4 min to diagnose on 2 cores.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib.model.effects import TruthEffects
from calib.report.diagnosis import format_diagnosis
from calib.twin import DISSERTATION_POSTURES, TwinPreset

pytestmark = pytest.mark.slow

TINY4 = TwinPreset(phantom_resolution_mm=14, truth_mesh_mm=10, spacing_mm=(2.0, 2.0, 2.0),
                   postures=DISSERTATION_POSTURES)  # fmt: skip
PAD_N = 0.2  # total force of the pad, N (the phantom weighs about 3.5 N)


def _pad_forces(mesh) -> dict:
    """Point loads of a 15 mm pad pushing the flank along -y (phantom frame), N."""
    x = mesh.nodes_mm
    surf = mesh.node_set("surface")
    band = surf[(x[surf, 2] > 15.0) & (x[surf, 2] < 35.0)]
    centre = x[band[np.argmax(x[band, 1])]]
    near = surf[np.linalg.norm(x[surf] - centre, axis=1) < 15.0]
    return {int(n): np.array([0.0, -PAD_N / len(near), 0.0]) for n in near}


def _build(root, name: str, effects: TruthEffects, *, pad_posture: int | None = None):
    import fem
    from calib.twin import synthesize
    from calib.workflows.calibrate import run_calibration
    from calib.workflows.diagnose import run_diagnosis

    out = root / name
    solve = fem.solve
    calls = []

    def padded(model, **kw):  # the truth solve of one posture gets the pad's loads
        calls.append(1)
        if len(calls) - 1 == pad_posture:
            kw["point_forces_n"] = _pad_forces(model.mesh)
        return solve(model, **kw)

    with pytest.MonkeyPatch.context() as mp:
        if pad_posture is not None:
            mp.setattr(fem, "solve", padded)
        synthesize(out / "twin", preset=TINY4, seed=0, effects=effects)
    from calib.fitting import CalibrationOptions

    options = CalibrationOptions(mesh_size_mm=14.0, mesh_retry_mm=(16.0,), profile_points=0)
    run_calibration(out / "twin" / "scans", out / "work", options)
    return out, run_diagnosis(out / "work")


@pytest.fixture(scope="module")
def skin(tmp_path_factory):
    return _build(tmp_path_factory.mktemp("twins"), "skin", TINY4.effects)


@pytest.fixture(scope="module")
def none(tmp_path_factory):
    return _build(tmp_path_factory.mktemp("twins"), "none", TruthEffects())


def test_the_hidden_skin_is_named(skin):
    out, doc = skin
    assert doc["verdict"].startswith("named: skin"), doc["verdict"]
    c1_true = json.loads((out / "twin" / "truth" / "truth.json").read_text())["material"]["c1_pa"]
    # the homogeneous calibration absorbs the skin into c1 ~ 1.3x the truth (555 Pa on
    # the quick twin); with the skin refitted c1 comes back within 5 % (issue 13's bar)
    assert doc["calibration"]["c1_pa"] > 1.2 * c1_true
    assert doc["c1_pa"] == pytest.approx(c1_true, rel=0.05)
    ratio = doc["refit"]["intervals"]["skin"]["ratio"]
    # the 8x skin at the library's 1.5 mm, on a 14 mm mesh: within a factor 2 of the
    # truth (the README's run of this twin: 7.79, 95 % interval 6.97-8.61; the element's
    # volume fractions and the band's thickness vary with the mesh, so not its interval).
    # The factor holds every quick seed's interval (README table, seeds 0-2: ratios
    # 6.7-8.1, the widest interval 4.2-9.3 on seed 1's 16 mm mesh)
    assert 4.0 < ratio < 16.0
    # what the surface sees: (ratio - 1) x the band's thickness, said in the summary
    iv = doc["refit"]["intervals"]["skin"]
    assert iv["excess_mm"] == pytest.approx((ratio - 1.0) * 1.5)
    assert iv["excess_ci95_mm"] == pytest.approx([(r - 1.0) * 1.5 for r in iv["ratio_ci95"]])
    assert "(ratio - 1) x thickness" in format_diagnosis(doc)
    # the twin renders every posture alike: one noise level (review W's per-scan levels)
    assert doc["noise"]["by_scan"] is False
    levels = doc["noise"]["scan_sd_mm"]
    assert set(levels) == set(doc["scans"]["diagnosis"])
    # the fitted scans' surface error falls
    for name in doc["scans"]["diagnosis"]:
        e = doc["gap"][name]["surface_error_mm"]
        assert e["after"]["mean"] < e["before"]["mean"]
    page = (out / "work" / "diagnosis" / "report.html").read_text()
    # review BY: each screening row says its test; the localisation's z is said pointwise
    assert "<th>test</th>" in page and "they do not enter the verdict" in page
    assert json.loads(json.dumps(doc, allow_nan=False))["effects"]["density"]["status"] == (
        "not identifiable"
    )


def test_the_refitted_model_is_a_calibration_validate_accepts(skin):
    from calib.data import read_work
    from calib.workflows.validate import run_validation

    out, doc = skin
    refit = out / "work" / "diagnosis" / "refit"
    wf = read_work(refit)
    assert wf.c1_pa == pytest.approx(doc["c1_pa"])
    assert wf.record["model"]["effects"]["named"] == ["skin"]
    assert "skin" in {n.split(":")[0] for n in wf.mesh.region_names}
    # its mesh record is the diagnosis' model mesh (was the calibration's, whatever ran)
    mesh = wf.record["mesh"]
    assert (mesh["size_mm"], mesh["n_tets"]) == (
        doc["model_mesh"]["size_mm"],
        doc["model_mesh"]["n_tets"],
    )
    assert mesh["n_tets"] == wf.mesh.n_tets
    assert mesh["max_dihedral_deg"] is doc["model_mesh"]["max_dihedral_deg"] is None
    assert mesh["failed_sizes"] == [] and mesh["formulation"] == "taylor-hood"
    calibration = json.loads((out / "work" / "calibration.json").read_text())
    assert wf.record["diagnosis"]["calibration_mesh"] == calibration["mesh"]
    # review AT: recorded as given (relative to wherever diagnose ran), then named wrongly
    assert wf.record["diagnosis"]["source_work"] == str((out / "work").resolve())
    val = run_validation(refit)
    assert set(val["scans"]) == set(doc["gap"])
    roles = {n: s["role"] for n, s in val["scans"].items()}
    assert roles[doc["scans"]["holdout"]] == "validation"
    # the calibration's model-fit verdict judged the model without the skin: not the
    # refit's (review AK: validate warned of the calibration's misfit on the refit)
    assert wf.record["model_fit"] is None and not any(
        "misfit" in c for c in val["calibration_caveats"]
    )


def test_a_refit_on_another_mesh_is_swept_as_its_own_states(skin, tmp_path):
    # review AU: diagnosed on another mesh than the calibration's, the refit's
    # reference_mesh.vtu held the null fit's stress-free geometry (solved after the final
    # model), and a sweep of it was 1.2-1.5 mm off the refit's own states. Two code paths:
    # the sweep's model of the refit against the states diagnose saved. Tolerance: both
    # Newton solves stop at rtol 1e-8 of the load (~1e-9 mm on ~15 mm)
    import shutil

    import meshio

    import fem
    from calib.discrepancy import DiagnosisOptions
    from calib.sweep import load_sweep_model
    from calib.workflows.diagnose import run_diagnosis

    out, _ = skin
    work = tmp_path / "work"
    shutil.copytree(out / "work", work)
    doc = run_diagnosis(work, DiagnosisOptions(mesh_size_mm=16.0))
    assert doc["model_mesh"]["size_mm"] == 16.0 and doc["calibration"]["mesh_note"]
    refit = work / "diagnosis" / "refit"
    record = json.loads((refit / "calibration.json").read_text())
    assert record["reference_state"] == "unload"  # its own straight reference
    m = load_sweep_model(refit)
    fm = m.fem_model()
    disc = fem.discretize(fm.mesh, fm.support, formulation=m.formulation)
    for name, scan in record["scans"].items():
        sol = fem.solve(fm, gravity=np.asarray(scan["gravity_ref"]), g_m_s2=m.g_m_s2, disc=disc)
        saved = meshio.read(refit / "calibration" / f"{name}_deformed.vtu")
        u = saved.point_data["displacement_mm"]
        assert np.linalg.norm(u, axis=1).max() > 5.0
        assert np.abs(sol.displacement_mm - u).max() < 1e-6, name


def test_a_homogeneous_truth_has_no_missing_effect(none):
    _, doc = none
    assert doc["verdict"] == "no missing effect"
    assert doc["named"] == []
    # the model mesh's facets lie inside the scanned surface on average (chords of a
    # convex body), by less than a 14 mm facet's sagitta on the body's ~50 mm radius
    # (h^2 / (8 R) = 0.49 mm), and the summary says by how much
    gap = doc["model_mesh"]["facet_gap_mm"]
    assert -0.49 < gap["mean"] < 0 < gap["sd"] and gap["n"] > 100
    assert f"facets lie {gap['mean']:+.3f} mm (sd {gap['sd']:.3f})" in format_diagnosis(doc)
    # and it says how large each physical effect would have to be to show
    summary = format_diagnosis(doc)
    for name, e in doc["effects"].items():
        if e["kind"] != "nuisance" and e["status"] == "identifiable":
            assert e["detectable"] > 0 and e["screen_unit"]
            assert f"{name} {e['detectable']:.3g} ({e['screen_unit']})" in summary


def test_the_skin_limit_in_its_own_ratio_lies_under_the_skin_the_twin_names(none):
    # --parameter-limits on the homogeneous twin, skin screened alone: the full-FE size of
    # the skin the scans would show. The preset's skin (x8) is named on the same postures
    # and mesh (test_the_hidden_skin_is_named), so the limit must be reached below x8;
    # a stiffer skin passes partly for a stiffer c1, so the planted bulk c1 that the null
    # fit takes for its own is lower at every size tried.
    from calib.data import read_work
    from calib.discrepancy import DiagnosisOptions, diagnose
    from calib.report.diagnosis import detection_limits

    out, _ = none
    opts = DiagnosisOptions(effects=("skin",), parameter_limits=True)
    d = diagnose(read_work(out / "work"), opts)
    lim = d.limits["skin"]
    assert lim.status == "reached" and 1.0 < lim.value < 8.0, lim
    assert all(ratio < 1.0 for _, _, ratio in lim.steps)
    doc = d.to_json()
    assert doc["effects"]["skin"]["parameter_limit"]["value"] == pytest.approx(lim.value)
    assert f"skin {lim.value:.3g} or more (skin c1 / bulk c1)" in detection_limits(doc)


def test_the_noise_model_against_the_twin_imaging_error(none):
    # the residual of the right model is the noise: the imaging's own error (measured
    # surface against the twin's true one, known here) plus the model mesh's faceting.
    # The variogram's sd must cover the first and not exceed the residual's own rms.
    import imaging
    from calib.model.residuals import closest_on_surface

    out, doc = none
    sd = doc["noise"]["model"]["sigma_mm"]
    err = []
    for name in doc["scans"]["diagnosis"]:
        true = imaging.read_ply(out / "twin" / "truth" / f"{name}_surface.ply")
        meas = imaging.read_ply(out / "work" / "scans" / name / "surface.ply")
        pts = meas.vertices_lps_mm[~np.asarray(meas.back_plate, bool)]
        c, _, _, n = closest_on_surface(true.vertices_lps_mm, true.faces, pts)
        d = np.einsum("kj,kj->k", pts - c, n)
        err.append(d - d.mean())
    imaging_sd = float(np.std(np.concatenate(err)))
    # the noise model's sd lies above the renderer's own and at most at the residual's
    # spread (noise is a part of it), with 10 % for the variogram fit's error (review
    # CF-18: the margin had no source)
    assert imaging_sd < sd <= 1.1 * doc["null_fit"]["rms_mm"]


def test_an_effect_outside_the_library_is_unexplained(tmp_path_factory):
    out, doc = _build(tmp_path_factory.mktemp("twins"), "pad", TruthEffects(), pad_posture=3)
    assert doc["verdict"] == "unexplained", (doc["verdict"], doc["candidates"])
    loc = doc["localisation"]["tilt_50"]
    # the pad's posture's map lights up (beyond |z| 4; where its largest |z| lies is not
    # checked here: review CF-21)
    assert loc["max_abs_z"] > 4.0


def _skin_and_null_again(skin, none, tmp_path, **options) -> dict:
    """Both twins diagnosed again with ``options`` on copies of their calibrations.

    The hidden skin must still be named with c1 back within 5 % of the truth (issue 13's
    bar) and the homogeneous truth get no name (0 false namings).
    """
    import shutil

    from calib.discrepancy import DiagnosisOptions
    from calib.workflows.diagnose import run_diagnosis

    opts = DiagnosisOptions(**options)
    docs = {}
    for name, (out, _) in {"skin": skin, "none": none}.items():
        work = tmp_path / name
        shutil.copytree(out / "work", work, ignore=shutil.ignore_patterns("diagnosis*"))
        docs[name] = run_diagnosis(work, opts)
    c1_true = json.loads((skin[0] / "twin" / "truth" / "truth.json").read_text())["material"]
    assert docs["skin"]["verdict"].startswith("named: skin"), docs["skin"]["verdict"]
    assert docs["skin"]["c1_pa"] == pytest.approx(c1_true["c1_pa"], rel=0.05)
    assert docs["none"]["named"] == [], docs["none"]["verdict"]
    return docs


def test_a_noise_profile_by_height_names_the_skin_and_nothing_on_the_null(skin, none, tmp_path):
    # --noise-profile plate on copies of the same two calibrations: the hidden skin is
    # still named with c1 back within 5 % (issue 13's bar), the homogeneous truth gets no
    # name (0 false namings), and the profile measured on the null twin's residual is
    # louder at the plate than far from it (the clamped edge: 2-4x on the quick null
    # twins, benchmarks/bench_diagnose.py --rim-profile)
    docs = _skin_and_null_again(skin, none, tmp_path, noise_profile="plate")
    prof = docs["none"]["noise"]["height_profile"]
    assert prof["relative_sd"][0] > 1.5 and prof["relative_sd"][-1] == 1.0
    assert docs["none"]["options"]["noise_profile"] == "plate"


def test_the_model_mesh_s_error_absorbed_names_the_skin_and_nothing_on_the_null(
    skin, none, tmp_path
):
    # --mesh-error absorbed on copies of the same two calibrations: every test also
    # conditions on the residual change to a mesh 1.4 times coarser (19.6 mm here). The
    # hidden skin is still named with c1 back within 5 % (issue 13's bar), the
    # homogeneous truth gets no name (0 false namings); the record says which mesh (its
    # element count 1.2-1.6 times coarser per edge: TetGen's sizing is loose) and how
    # large the change was (at least 0.02 mm rms: the dissertation twins' 12 -> 16.8 mm
    # change was 0.05-0.25 mm, docs/diagnose-evidence.md, "The model mesh's own error as
    # a nuisance"), and the column acted: the null's screen statistics differ from the default's
    docs = _skin_and_null_again(skin, none, tmp_path, mesh_error="absorbed")
    for doc in docs.values():
        rec = doc["model_mesh"]["error"]
        assert rec["status"] == "absorbed", rec
        assert rec["size_mm"] == pytest.approx(1.4 * doc["model_mesh"]["size_mm"], abs=0.05)
        assert 1.2 < rec["effective_factor"] < 1.6, rec
        assert set(rec["rms_mm"]) == set(doc["scans"]["diagnosis"])
        assert all(v > 0.02 for v in rec["rms_mm"].values()), rec
        assert np.isfinite(rec["amplitude"]) and rec["standard_error"] > 0
        assert "discretisation" not in {c["name"] for c in doc["screening"]["columns"]}
    before = {c["name"]: c["statistic"] for c in none[1]["screening"]["columns"]}
    after = {c["name"]: c["statistic"] for c in docs["none"]["screening"]["columns"]}
    assert any(
        abs(after[k] - before[k]) > 0.01 * abs(before[k])
        for k in before
        if before[k] is not None and after.get(k) is not None  # None: not identifiable
    )


def test_the_model_error_bench_rereads_the_share_and_what_the_skin_adds(skin, none, tmp_path):
    # benchmarks/bench_diagnose.py --model-error: the diagnosis' share explained, read
    # again by FE re-solves at the refit's parameters (a second code path), and the share
    # of what the hidden skin adds over the null twin of the same seed
    from test_diagnose import _bench_module

    bench = _bench_module()
    (tmp_path / "skin").symlink_to(skin[0])
    (tmp_path / "none-s0").symlink_to(none[0])
    m = bench.model_error(tmp_path, {"case": "skin", "seed": 0, "hidden": "skin"})
    c = m["candidate"]
    assert c["effect"] == "skin" and c["round"] == 1
    # the diagnosis judged with the smallest short-range noise variance of the fits
    # refitted up to then, the bench with the smallest of all (diagnosis.json): a few per
    # cent of the floor, about one point of share on the quick twins (47/47 %, 92/91 %).
    # A physical effect's share is the larger of two (beyond the margin, every point)
    if c["explained"] > c["explained_all_points"]:
        assert m["share"] == pytest.approx(c["explained"], abs=0.03)
    else:
        assert m["share"] <= c["explained"] + 0.03
    assert m["margin_mm"] == skin[1]["scans"]["explained_margin_mm"]
    # the null twin keeps its model's own error: nothing removes it, so the skin's refit
    # removes more of what the skin adds than of the residual above the noise floor
    assert m["ms_mm2"]["null"] > m["ms_mm2"]["floor"]
    assert m["share_of_added"] > m["share"] > 0.5


def test_the_mesh_series_refits_the_diagnosis_on_its_own_mesh(none, tmp_path):
    # benchmarks/bench_diagnose.py --mesh-series: the c1-only fit on a model mesh rebuilt
    # from the reference scan at the diagnosis' size (build_problem's mesh_size_mm)
    # against the diagnosis' own null fit. Where the calibration's reference is straight
    # that is the calibration's own mesh (a second code path; measured 0.0842 mm both
    # ways, quick null twin seed 0, 14 mm); this tiny twin's calibration went prestressed,
    # so both rebuild the next size. The same TetGen input gives the same mesh and the
    # same fit: the bar, 0.1 % of the mean square, is the c1 fit's tolerance.
    from test_diagnose import _bench_module

    bench = _bench_module()
    (tmp_path / "none").symlink_to(none[0])
    work = tmp_path / "none" / "work"
    doc = json.loads((work / "diagnosis.json").read_text())
    plain = bench._judged_ms(work, doc, [None])
    (row,) = bench.mesh_series(tmp_path, {"case": "none"}, [plain["mesh_size_mm"]])
    assert row["mesh_size_mm"] == plain["mesh_size_mm"]
    assert row["ms_mm2"] == pytest.approx(plain["fits"][0]["ms_mm2"], rel=1e-3)
    assert row["c1_pa"] == pytest.approx(plain["fits"][0]["c1_pa"], rel=1e-3)
    assert set(row["scans_ms_mm2"]) == set(doc["scans"]["diagnosis"])
    assert row["ms_mm2"] > row["floor_ms_mm2"]  # the model's own error stays above it
