"""The diagnosis' statistics and decisions on cheap linear models (no FE).

False-positive rate of the screening on simulated null residuals with correlated noise
(seeded, many draws, a binomial band), power on a planted effect, the per-scan offset
nuisance, the local z-map's calibration and localisation of a planted bump, first-order
leave-one-posture-out against its closed form, the verdict strings, and the command's
errors. The whole workflow on digital twins: ``test_diagnose_twins.py`` (slow).
"""

from __future__ import annotations

import importlib
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.cli import app
from calib.discrepancy import DiagnosisError, DiagnosisOptions
from calib.discrepancy.diagnose import _verdict
from calib.discrepancy.fields import Column, FieldSet
from calib.discrepancy.localise import region_labels, significance_map
from calib.discrepancy.refit import PHYSICAL, Refit, lopo, sliding_ln_k_bounds
from calib.discrepancy.screen import screen
from calib.fitting import CalibrationOptions
from calib.fitting.options import MESH_SIZE_RANGE_MM
from calib.model.effects import LIBRARY, EffectValues
from calib.stats.coverage import NoiseSampler, misfit_pattern, phantom_sample, sag_sensitivity
from calib.stats.noise import NoiseModel

SCANS = ("a", "b")


def _fields(sample, r, J, columns: dict) -> FieldSet:
    blocks = {n: idx for n, idx in zip(SCANS, sample.blocks, strict=True)}
    cols = tuple(
        Column(k, k, None, "p", {n: v[blocks[n]] for n in SCANS}) for k, v in columns.items()
    )
    return FieldSet(
        SCANS, {n: r[blocks[n]] for n in SCANS}, {n: J[blocks[n]] for n in SCANS}, cols, {}
    )


def _points(sample):
    return {n: sample.points_mm[idx] for n, idx in zip(SCANS, sample.blocks, strict=True)}


@pytest.fixture(scope="module")
def linear():
    sample = phantom_sample(250, 2, seed=11)
    J = sag_sensitivity(sample, posture_deg=(180.0, 50.0))
    # candidate fields: a -dr/dp convention like the FE fields (screen negates them)
    cols = {
        "p2": -misfit_pattern(sample),
        "tilt": -misfit_pattern(sample, kind="tilt"),
        "bump": -misfit_pattern(sample, kind="bump"),
    }
    truth = NoiseModel("exponential", 0.2, 0.1, 8.0)
    return sample, J, cols, NoiseSampler.of(sample, truth)


def _at_fit(J, x):
    """The residual at the least-squares fit of ln c1 alone (as the null fit leaves it)."""
    return x - J * float(J @ x) / float(J @ J)


def screen_null_alarms(linear, draws: int) -> dict[str, list[bool]]:
    """Per seeded null draw (with each scan's offset), the screen's and misfit test's alarms.

    The test below and ``benchmarks/bench_rate_tests.py`` (its long run) both draw here.
    """
    sample, J, cols, sampler = linear
    offset = np.where(sample.scan == 0, 0.1, -0.05)
    rng = np.random.default_rng(7)
    out = {"family-wise": [], "misfit": [], **{name: [] for name in cols}}
    for _ in range(draws):
        r = _at_fit(J, sampler.draw(rng)[:, 0] + offset)
        s = screen(_fields(sample, r, J, cols), _points(sample), alpha=0.05)
        out["family-wise"].append(any(e.significant for e in s.screening.effects))
        out["misfit"].append(s.misfit.verdict == "misfit")
        for e in s.screening.effects:
            out[e.name].append(e.p_value < 0.05)
    return out


def test_screening_false_positive_rate_on_correlated_null_residuals(linear):
    # no effect; noise correlated over 8 mm (exponential, nugget 0.1) and a constant offset
    # per scan (+0.1 / -0.05 mm, like a segmentation threshold: absorbed, never an effect).
    # 400 seeded draws at alpha = 0.05: the family-wise (Holm) rate and each column's
    # unadjusted rate at most 5 % + 3 binomial se (1.09 %), i.e. 8.3 %: a rate of 10 %
    # passes with probability 0.14 (review CF-9: 200 draws passed it with 0.47). Long run
    # (`python benchmarks/bench_rate_tests.py --only diagnose`, 2000 draws): family-wise 4.0 %, the
    # columns 4.65, 4.4, 4.55 %, the misfit test 1.45 %.
    alarms = screen_null_alarms(linear, 400)
    assert len(alarms) == 2 + len(linear[2]) and all(len(a) == 400 for a in alarms.values())
    bound = 0.05 + 3 * np.sqrt(0.05 * 0.95 / 400)
    rates = {name: float(np.mean(a)) for name, a in alarms.items()}
    assert all(rate <= bound for rate in rates.values()), rates


def test_screening_finds_a_planted_effect_and_its_size(linear):
    # 'tilt' at 0.15 mm RMS (0.75 noise sd): significant after Holm in each of 5 draws,
    # the others not; the one-step estimate (a parameter step: the fields are -dr/dp)
    # within 3 standard errors of the planted 0.15
    sample, J, cols, sampler = linear
    rng = np.random.default_rng(8)
    for _ in range(5):
        r = _at_fit(J, sampler.draw(rng)[:, 0] + 0.15 * misfit_pattern(sample, kind="tilt"))
        s = screen(_fields(sample, r, J, cols), _points(sample))
        by = {e.name: e for e in s.screening.effects}
        assert by["tilt"].significant and not by["p2"].significant
        assert by["tilt"].estimate == pytest.approx(0.15, abs=3 * by["tilt"].standard_error)


def test_the_regions_scale_with_the_body_s_height(monkeypatch):
    # audit M: on a body 0.7 times the twin's (52.3 mm tall) the 20 / 10 / 15 mm radii put
    # 61 % of the diagnosed points "over inclusions" (22 % on the twin). Closed form: the
    # height over 75 mm to one decimal, 1 for the twins' 71-78 mm (their regions as
    # before), 0.7 and 1.4 for the 0.7x and 1.4x twins (52.3 and 103.7 mm)
    import importlib

    from calib.model.reference import body_scale as region_scale

    dg = importlib.import_module("calib.discrepancy.diagnose")

    assert [region_scale(h) for h in (71.3, 74.5, 78.7, 52.3, 103.7)] == [1, 1, 1, 0.7, 1.4]
    with pytest.raises(ValueError, match="body height must be positive"):
        region_scale(0.0)
    seen = {}
    monkeypatch.setattr(dg, "region_labels", lambda p, **kw: seen.update(kw))
    scan = SimpleNamespace(
        T_ref_from_scan=np.eye(4),
        tumour_mm=np.zeros(3),
        nipple_mm=np.ones(3),
        back_point_mm=np.zeros(3),
        back_normal=np.array([0.0, 0.0, -1.0]),
    )
    work = SimpleNamespace(path="WORK")
    prob = SimpleNamespace(
        measurement=lambda n: scan, work=work, region_scale=region_scale(52.3), rim_margin_mm=5.0
    )
    monkeypatch.setattr(dg, "ingest_record", lambda work, name: {})
    dg._scan_regions(prob, "s", np.zeros((1, 3)))
    assert seen["apex_mm"] == pytest.approx(14.0) and seen["over_mm"] == pytest.approx(10.5)
    assert seen["rim_mm"] == pytest.approx(7.0) and seen["spheres"][0][1] == pytest.approx(7.0)


def test_a_region_of_many_points_counts_their_correlation():
    # a region of more than 4000 points took its mean's variance as sigma^2 / n
    # (independent points), against sigma^2 sum_ij R_ij / n^2 below that: here (5 mm
    # correlation, a point every 6 mm) z 6.40 for 3.14; with a point every 1.5 mm, 7 times
    # too large. Two code paths: the dense covariance's sum of the same points (134 MB)
    # against the region's z (exact but for round-off: rel 1e-9)
    from calib.discrepancy.localise import _local_cov

    rng = np.random.default_rng(0)
    n = 4100
    p = np.column_stack([rng.uniform(0.0, 400.0, (n, 2)), np.zeros(n)])
    noise = NoiseModel("exponential", 0.1, 0.2, 5.0)
    m = significance_map("s", p, np.full(n, 0.01), np.full(n, "bulk"), noise)
    (bulk,) = [g for g in m.regions if g.region == "bulk"]
    dense = float(_local_cov(noise, p).sum()) / n**2
    assert bulk.z == pytest.approx(0.01 / np.sqrt(dense), rel=1e-9)


def test_local_z_map_is_calibrated_and_finds_a_bump_at_the_rim():
    # null: the share of points with |z| > 1.96 is 5 % in expectation under the true
    # model; the z's of one draw are correlated over the kernel, so the share varies more
    # than binomially: over 30 other draws its mean was 5.8 %, its sd 4.0 %, so the mean of
    # 10 has an sd of 1.3 % and 2-10 % is the expectation +- 3 of them.
    sample = phantom_sample(1500, 1, seed=3)
    p = sample.points_mm
    noise = NoiseModel("exponential", 0.1, 0.2, 5.0)
    sampler = NoiseSampler.of(sample, noise)
    labels = region_labels(
        p,
        nipple_mm=np.array([0.0, 0.0, 60.0]),
        back_point_mm=np.zeros(3),
        back_normal=np.array([0.0, 0.0, -1.0]),
        spheres=[],
    )
    rng = np.random.default_rng(4)
    shares = []
    for _ in range(10):
        m = significance_map("s", p, sampler.draw(rng)[:, 0], labels, noise)
        shares.append(np.mean(np.abs(m.z) > 1.96))
    assert 0.02 <= np.mean(shares) <= 0.10
    # a 0.3 mm bump of 12 mm at the apex: the apex's mean is significant, the rim's is not,
    # and the map's largest z lies within 15 mm of the bump; on the flank, the largest z
    # follows the bump there. Over 10 other draws: the apex's p at most 5e-5 (1e-3 leaves
    # a factor 20), the largest z within 5.2 mm of the bump (15 mm: 1.25 of its widths);
    # the rim lies beyond the bump's reach, its p is the null's (above 0.01 in 99 % of
    # draws: this seeded one 0.01 < p)
    centre = np.array([0.0, 0.0, 60.0])
    bump = 0.3 * np.exp(-0.5 * np.sum((p - centre) ** 2, axis=1) / 12.0**2)
    m = significance_map("s", p, sampler.draw(rng)[:, 0] + bump, labels, noise)
    reg = {r.region: r for r in m.regions}
    assert reg["apex"].p_value < 1e-3 and reg["rim"].p_value > 0.01
    assert np.linalg.norm(p[np.argmax(m.z)] - centre) < 15.0
    flank = np.array([-53.0, 0.0, 42.0])  # on the ellipsoid: (53/75)^2 + (42/60)^2 ~ 1
    bump = 0.3 * np.exp(-0.5 * np.sum((p - flank) ** 2, axis=1) / 12.0**2)
    m = significance_map("s", p, sampler.draw(rng)[:, 0] + bump, labels, noise)
    assert np.linalg.norm(p[np.argmax(m.z)] - flank) < 15.0
    assert set(m.as_json()["regions"]) == {"apex", "rim", "inclusions", "bulk"}


def _refit(sample, r, J, cols: dict, x) -> Refit:
    from calib.discrepancy.problem import Nuisance

    fs = _fields(sample, r, J, cols)
    names = ("theta", *cols)
    n = len(x)
    nuisance = {s: Nuisance() for s in SCANS}  # every scan's, as refit's unpack_parameters gives
    for name, v in zip(cols, x[1:], strict=True):
        if name.startswith("gravity["):
            scan, k = name[8:].split("].a")
            nuisance[scan].gravity_rad[int(k)] = v
    return Refit(
        tuple(cols),
        float(x[0]),
        EffectValues(),
        nuisance,
        names,
        np.asarray(x, float),
        np.full(n, -np.inf),
        np.full(n, np.inf),
        fs,
        float(r @ r),
        float(r @ r) / len(r),
        1,
        1,
        0,
        True,
        "",
    )


def test_lopo_is_exact_for_a_linear_model_and_prefers_the_right_one(linear):
    # data r(x) = r0 + A (x - x_true) with the effect in them: at the joint fit the
    # residual is zero and every left-out scan is predicted exactly (first order is exact
    # for a linear model); the c1-only model cannot predict the effect: LOPO error > 0
    sample, J, cols, _ = linear
    s = cols["tilt"]
    data = 0.2 * s  # the scans ask for 0.2 of the 'tilt' field, beyond c1
    joint = _refit(sample, np.zeros(sample.n), J, {"tilt": s}, [0.0, 0.2])
    assert lopo(joint)["mean_sq_mm2"] == pytest.approx(0.0, abs=1e-20)
    coef = float(J @ data) / float(J @ J)
    null = _refit(sample, data - J * coef, J, {}, [coef])
    # the c1-only model's leave-one-scan-out by hand: the scalar least squares of the other
    # scan's residual on its c1 column, both less their means (each scan's offset is a
    # nuisance), predicting the left-out scan less its mean; exact for a linear model, so
    # rel 1e-9 (rounding) tells it from the in-sample mean square 0.0400 (review CF-2: a
    # bar of > 1e-3 let that through; the leave-one-out is 0.0421 mm^2)
    r = data - J * coef
    blocks = dict(zip(SCANS, sample.blocks, strict=True))
    centred = {n: (r[i] - r[i].mean(), J[i] - J[i].mean()) for n, i in blocks.items()}
    by_hand = {}
    for n in SCANS:
        [(r_o, j_o)], (r_k, j_k) = [centred[m] for m in SCANS if m != n], centred[n]
        pred = r_k - j_k * float(j_o @ r_o) / float(j_o @ j_o)
        by_hand[n] = float(np.mean(pred**2))
    out = lopo(null)
    assert out["per_scan"] == pytest.approx(by_hand, rel=1e-9)
    sizes = {n: len(i) for n, i in blocks.items()}
    pooled = sum(by_hand[n] * sizes[n] for n in SCANS) / sum(sizes.values())
    assert out["mean_sq_mm2"] == pytest.approx(pooled, rel=1e-9)
    assert out["mean_sq_mm2"] > 1.02 * float(np.mean(r**2))  # beyond the in-sample fit


def test_verdict_strings(linear):
    sample, J, cols, sampler = linear
    o = DiagnosisOptions()
    rng = np.random.default_rng(9)
    null = screen(_fields(sample, _at_fit(J, sampler.draw(rng)[:, 0]), J, cols), _points(sample))
    assert _verdict([], [], null, None, o) == "no missing effect"
    # a pattern none of the screened fields carries ('bump', 30 mm at the apex, 0.8 mm RMS:
    # 4 noise sd; the misfit test at its 1 % level flags it)
    r = _at_fit(J, sampler.draw(rng)[:, 0] + 0.8 * misfit_pattern(sample, kind="bump"))
    outside = screen(_fields(sample, r, J, {"tilt": cols["tilt"]}), _points(sample))
    assert outside.misfit.verdict == "misfit"
    assert _verdict([], [], outside, None, o) == "unexplained"
    # only a field that c1 absorbs (like density): not identifiable
    only = screen(_fields(sample, r, J, {"density": -J}), _points(sample))
    assert only.screening.not_identifiable == ("density",)
    od = DiagnosisOptions(effects=("density",))
    assert _verdict([], [], only, None, od) == "not identifiable from these data: density"
    assert _verdict(["skin"], [], outside, null, o) == "named: skin"
    assert _verdict(["skin"], ["inclusions"], outside, null, o) == (
        "named: skin | inclusions (confounded)"
    )
    assert _verdict(["skin"], [], outside, outside, o) == "named: skin (+ unexplained remainder)"


def test_options_are_checked():
    with pytest.raises(DiagnosisError, match="unknown effect"):
        DiagnosisOptions(effects=("wrinkles",))
    with pytest.raises(DiagnosisError, match="twice"):
        DiagnosisOptions(effects=("skin", "skin"))
    with pytest.raises(DiagnosisError, match="alpha"):
        DiagnosisOptions(alpha=0.7)


def test_diagnose_takes_the_mesh_sizes_calibrate_takes():
    # One range for both: a calibration on 1 or 50 mm can be diagnosed on its own size.
    lo, hi = MESH_SIZE_RANGE_MM
    for size in (lo, hi):
        CalibrationOptions(mesh_size_mm=size)
        DiagnosisOptions(mesh_size_mm=size, inclusion_mesh_mm=size)
    for size in (0.99 * lo, 1.01 * hi):
        with pytest.raises(ValueError, match=r"^mesh_size_mm \(--mesh-size\) must lie in"):
            CalibrationOptions(mesh_size_mm=size)
        with pytest.raises(DiagnosisError, match=r"mesh_size_mm \(--mesh-size\) must lie in"):
            DiagnosisOptions(mesh_size_mm=size)


def test_command_help_and_errors(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["diagnose", "--help"])
    assert res.exit_code == 0 and "--holdout" in res.output and "--effects" in res.output
    assert "--mesh-size" in res.output and "--parameter-limits" in res.output
    res = runner.invoke(app, ["diagnose", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "nowhere: no such folder" in res.output
    res = runner.invoke(app, ["diagnose", str(tmp_path)])
    assert res.exit_code == 2 and "no calibration.json" in res.output
    res = runner.invoke(app, ["diagnose", str(tmp_path), "--effects", "skin,wrinkles"])
    assert res.exit_code == 2 and "unknown effect" in res.output
    res = runner.invoke(app, ["diagnose", str(tmp_path), "--rim-margin", "wide"])
    assert res.exit_code == 2 and "--rim-margin must be a width in mm or 'element'" in res.output
    assert "--inclusion-mesh" in runner.invoke(app, ["diagnose", "--help"]).output
    res = runner.invoke(
        app, ["diagnose", str(tmp_path), "--mesh-size", "10", "--inclusion-mesh", "12"]
    )
    assert (
        res.exit_code == 2
        and "inclusion_mesh_mm (--inclusion-mesh) must lie in [1, 50] mm" in res.output
    )
    res = runner.invoke(app, ["diagnose", str(tmp_path), "--skin-thickness", "0"])
    assert (
        res.exit_code == 2
        and "skin_thickness_mm (--skin-thickness) must lie in (0, 10] mm" in res.output
    )


def test_a_mesh_without_a_straight_reference_is_replaced_and_the_note_says_why(monkeypatch):
    # quick homogeneous twin, seed 2, 14 mm: the calibration recovered a straight
    # stress-free reference, a cold recovery at its c1 in the diagnosis does not; the
    # diagnosis moves to the next size and says why (it raised a traceback before)

    import calib.model.reference as reference
    import fem
    from calib.discrepancy.problem import _straight_model

    monkeypatch.setattr(reference, "reference_mesh", lambda ref, size_mm, max_dihedral_deg: size_mm)

    class Model:
        def __init__(self, size):
            self.size = size

        def stress_free(self, theta):
            if self.size < 15.0:
                raise fem.ConvergenceError("inverse Newton stopped at load factor 0.93")

    work = SimpleNamespace(
        path="WORK", measurements=SimpleNamespace(reference=None), record={"c1_pa": 423.4}
    )
    why = "its recovery fails at the calibrated c1: load factor 0.93"
    params = {"mesh_size_mm": 14.0, "mesh_retry_mm": [16.0]}
    fm, note, size, bound, failed = _straight_model(work, params, Model, own_size=False, why=why)
    assert fm.size == size == 16.0 and bound is None  # meshed as the calibration's
    assert failed == []  # the calibration's own mesh is not tried again
    assert note == (
        f"the calibration's 14 mm mesh admits no straight stress-free reference ({why}); "
        "diagnosed on the 16 mm mesh"
    )
    with pytest.raises(DiagnosisError, match=r"calibration's mesh \(its recovery fails.*13 mm"):
        _straight_model(
            work, {"mesh_size_mm": 11.0, "mesh_retry_mm": [13.0]}, Model, own_size=False, why=why
        )


def test_meshes_with_fewer_slivers_are_tried_before_a_diagnosis_is_refused(monkeypatch):
    # a twin 1.4 times the usual size (c1 507 Pa): its 12, 14 and 16 mm meshes admit no
    # straight stress-free reference (the inverse Newton stops at load factor 0.96, 0.70,
    # 0.77: rim slivers) and the diagnosis was refused; meshed with TetGen's 165 deg
    # dihedral bound, the 12 mm one recovers (8 vertex tetrahedra inverted, 364 s). The
    # sizes are tried again with that bound, the calibration's own first, and the note
    # says so; a calibration meshed with a bound as tight is not retried
    import calib.model.reference as reference
    import fem
    from calib.discrepancy.problem import STRAIGHT_RETRY_DIHEDRAL_DEG, _straight_model

    built = []

    def mesh(ref, size_mm, max_dihedral_deg):
        built.append((size_mm, max_dihedral_deg))
        return size_mm, max_dihedral_deg

    monkeypatch.setattr(reference, "reference_mesh", mesh)

    class Model:
        def __init__(self, loaded):
            self.size, self.bound = loaded

        def stress_free(self, theta):
            if self.bound is None or self.bound > 165.0:
                raise fem.ConvergenceError("inverse Newton stopped at load factor 0.96")

    work = SimpleNamespace(
        path="WORK", measurements=SimpleNamespace(reference=None), record={"c1_pa": 507.0}
    )
    params = {"mesh_size_mm": 12.0, "mesh_retry_mm": []}
    lines = []  # each try is said before it starts: on a large body each takes minutes
    fm, note, size, bound, failed = _straight_model(
        work, params, Model, own_size=False, say=lines.append
    )
    assert lines == [
        "  recovering a straight stress-free reference at the calibrated c1 on a 14 mm model mesh",
        "  recovering a straight stress-free reference at the calibrated c1 on a 16 mm model mesh",
        "  recovering a straight stress-free reference at the calibrated c1 on a 12 mm model mesh"
        " with a 165 deg dihedral bound",
    ]
    assert STRAIGHT_RETRY_DIHEDRAL_DEG == 165.0
    assert (fm.size, fm.bound, size) == (12.0, 165.0, 12.0)
    assert bound == 165.0  # the refit's record says it (review N: it said the calibration's)
    assert [s for s, _ in failed] == [14.0, 16.0]  # and the meshes tried before
    assert built == [(14.0, None), (16.0, None), (12.0, 165.0)]
    assert note.startswith("no straight stress-free reference on the calibration's mesh (its ")
    assert "14 mm: inverse Newton stopped at load factor 0.96; 16 mm: " in note
    assert note.endswith(
        "diagnosed on the 12 mm mesh with TetGen's dihedral bound 165 deg (the calibration's: none)"
    )
    built.clear()
    tight = {**params, "mesh_max_dihedral_deg": 160.0}

    class Stuck(Model):
        def stress_free(self, theta):
            raise fem.ConvergenceError("inverse Newton stopped at load factor 0.7")

    with pytest.raises(DiagnosisError, match=r"nor on other meshes \(14 mm: .*16 mm: "):
        _straight_model(
            SimpleNamespace(
                **{**vars(work), "record": {"c1_pa": 507.0, "provenance": {"parameters": tight}}}
            ),
            tight,
            Stuck,
            own_size=False,
        )
    assert built == [(14.0, 160.0), (16.0, 160.0)]
    built.clear()
    with pytest.raises(DiagnosisError, match=r"12 mm: with a 165 deg dihedral bound: inverse"):
        _straight_model(work, params, Stuck, own_size=False)
    assert built == [(14.0, None), (16.0, None), (12.0, 165.0), (14.0, 165.0), (16.0, 165.0)]
    # TetGen failing with the bound on one size is one more failed try (review N: it
    # stopped the retry and said the calibration's own mesh could not be built), and the
    # note keeps the bounded failures apart from the meshes built as the calibration's
    built.clear()

    def mesh_or_none(ref, size_mm, max_dihedral_deg):
        if (size_mm, max_dihedral_deg) == (12.0, 165.0):
            raise fem.MeshError("tetgen: failed")
        return mesh(ref, size_mm, max_dihedral_deg)

    monkeypatch.setattr(reference, "reference_mesh", mesh_or_none)
    fm, note, size, bound, failed = _straight_model(work, params, Model, own_size=False)
    assert (fm.size, fm.bound, size, bound) == (14.0, 165.0, 14.0, 165.0)
    assert failed[2] == (
        12.0,
        "with a 165 deg dihedral bound: TetGen built no mesh: tetgen: failed",
    )
    assert (
        "0.96; 16 mm: inverse Newton stopped at load factor 0.96); with the bound, 12 mm: "
        "TetGen built no mesh: tetgen: failed; diagnosed on the 14 mm mesh with TetGen's " in note
    )


def test_a_prestressed_calibration_s_own_mesh_is_the_size_it_ran_on(monkeypatch):
    # review O: a calibration asked for 12 mm that fell back to 14 mm ran on 14 mm; the
    # diagnosis tried 12 mm as "its own" and said so. Its own is the size it ran on
    import calib.model.reference as reference
    from calib.discrepancy.problem import _straight_model

    built = []  # each size meshed; every recovery succeeds
    monkeypatch.setattr(
        reference, "reference_mesh", lambda ref, size_mm, max_dihedral_deg: built.append(size_mm)
    )

    def Model(loaded):  # stands in for the model class
        return SimpleNamespace(stress_free=lambda theta: None)

    record = {"c1_pa": 420.0, "mesh": {"size_mm": 14.0}}
    work = SimpleNamespace(path="WORK", measurements=SimpleNamespace(reference=None), record=record)
    params = {"mesh_size_mm": 12.0, "mesh_retry_mm": [14.0, 16.0]}
    chosen = _straight_model(work, params, Model, own_size=True)
    assert built == [14.0] and chosen.size_mm == 14.0
    assert chosen.note.endswith("on its own 14 mm mesh")
    built.clear()
    _straight_model(work, params, Model, own_size=False)  # its own failed: the next one
    assert built == [16.0]
    # no other size to try: straight to the bound, and the note lists no empty tries
    chosen = _straight_model(work, {**params, "mesh_retry_mm": [14.0]}, Model, own_size=False)
    assert (chosen.size_mm, chosen.max_dihedral_deg, chosen.failed) == (14.0, 165.0, [])
    assert "()" not in chosen.note and "nor on others" not in chosen.note


def test_a_mesh_size_asked_for_is_built_from_the_reference_scan_and_said(monkeypatch):
    import calib.model.reference as reference
    import fem
    from calib.discrepancy.problem import _sized_model

    monkeypatch.setattr(
        reference,
        "reference_mesh",
        lambda ref, size_mm, max_dihedral_deg: (ref, size_mm, max_dihedral_deg),
    )

    class Model:
        def __init__(self, mesh):
            self.mesh, self.theta = mesh, None

        def stress_free(self, theta):
            if self.mesh[1] > 30.0:
                raise fem.ConvergenceError("inverse Newton stopped at load factor 0.5")
            self.theta = theta

    # the calibration meshed with TetGen's bound on the largest dihedral angle
    record = {"c1_pa": 423.4, "provenance": {"parameters": {"mesh_max_dihedral_deg": 165.0}}}
    work = SimpleNamespace(
        path="WORK", measurements=SimpleNamespace(reference="ref"), record=record
    )
    fm, note, size, _, _ = _sized_model(work, {"mesh_size_mm": 14.0}, Model, 10.0)
    assert size == 10.0
    # the reference scan's mesh of that size, meshed as the calibration's, recovered at
    # the calibrated c1
    assert fm.mesh == ("ref", 10.0, 165.0) and fm.theta == pytest.approx(np.log(423.4))
    assert note == "diagnosed on a 10 mm mesh, as asked (the calibration's: 14 mm)"
    with pytest.raises(DiagnosisError, match=r"32 mm model mesh.*load factor 0.5.*--mesh-size"):
        _sized_model(work, {"mesh_size_mm": 14.0}, Model, 32.0)  # bound as tight: no retry
    # a calibration without the bound: the size asked for is meshed again with it before
    # it is refused (the quick twin's 9 mm mesh stops at load factor 0.695 without it)
    record = {"c1_pa": 423.4, "provenance": {"parameters": {}}}
    work = SimpleNamespace(path="WORK", measurements=SimpleNamespace(reference="r"), record=record)

    class Slivers(Model):
        def stress_free(self, theta):
            if self.mesh[2] is None:
                raise fem.ConvergenceError("inverse Newton stopped at load factor 0.695")

    fm, note, size, bound, failed = _sized_model(work, {"mesh_size_mm": 12.0}, Slivers, 9.0)
    assert fm.mesh == ("r", 9.0, 165.0) and (size, bound) == (9.0, 165.0)
    assert failed == [(9.0, "inverse Newton stopped at load factor 0.695")]
    assert note == (
        "no straight stress-free reference on a 9 mm model mesh at the calibrated c1 (inverse "
        "Newton stopped at load factor 0.695); diagnosed on the 9 mm mesh with TetGen's "
        "dihedral bound 165 deg (the calibration's: 12 mm)"
    )
    with pytest.raises(DiagnosisError, match="mesh_size_mm"):
        DiagnosisOptions(mesh_size_mm=0.5)


def test_inclusions_meshed_as_spheres_are_passed_on_and_said(monkeypatch):
    # diagnose --inclusion-mesh: the segmented inclusions go to reference_mesh as spheres
    # with their element size; a sphere that cannot be meshed is a DiagnosisError naming
    # the mesh, not a traceback; the options refuse an inner size above the mesh's
    import calib.model.reference as reference
    import fem
    from calib.discrepancy.problem import _sized_model

    def mesh(ref, size_mm, max_dihedral_deg, spheres=(), sphere_size_mm=None):
        if sphere_size_mm == 3.0:
            raise fem.MeshError("inclusion at [0, 0, 46] mm reaches the surface")
        return (size_mm, len(spheres), sphere_size_mm)

    monkeypatch.setattr(reference, "reference_mesh", mesh)

    class Model:
        def __init__(self, mesh):
            self.mesh = mesh

        def stress_free(self, theta):
            pass

    ref = SimpleNamespace(reference="ref")
    work = SimpleNamespace(path="WORK", measurements=ref, record={"c1_pa": 423.4})
    spheres = [((0.0, 0.0, 20.0), 12.0), ((10.0, 0.0, 30.0), 8.0), ((0.0, 9.0, 9.0), 4.0)]
    fm, note, size, _, _ = _sized_model(work, {"mesh_size_mm": 14.0}, Model, 14.0, (spheres, 5.0))
    assert fm.mesh == (14.0, 3, 5.0)
    said = "with its 2 inclusions 5 mm or wider meshed as spheres of 5 mm, as asked"
    assert note == f"diagnosed on a 14 mm mesh {said} (the calibration's: 14 mm)"
    with pytest.raises(DiagnosisError, match=r"no 14 mm model mesh with its 3 .*reaches the"):
        _sized_model(work, {"mesh_size_mm": 14.0}, Model, 14.0, (spheres, 3.0))
    with pytest.raises(DiagnosisError, match=r"inclusion_mesh_mm \(--inclusion-mesh\) must lie in"):
        DiagnosisOptions(mesh_size_mm=10.0, inclusion_mesh_mm=12.0)


def test_inclusions_meshed_on_the_calibrations_size_fall_back_as_the_plain_mesh_does(
    monkeypatch,
):
    # quick x30 inclusions twin, seed 1: its 14 mm mesh with 4 mm spheres had no straight
    # stress-free reference at the calibrated c1, and diagnose --inclusion-mesh stopped
    # where the plain diagnosis moves on to 16 mm. Now the calibration's size gives way
    # to its next sizes (said in the note); a size asked for with --mesh-size does not
    import calib.model.reference as reference
    import fem
    from calib.discrepancy.problem import _sized_model, next_mesh_sizes

    def mesh(ref, size_mm, max_dihedral_deg, spheres=(), sphere_size_mm=None):
        return size_mm

    monkeypatch.setattr(reference, "reference_mesh", mesh)

    class Model:
        def __init__(self, mesh):
            self.mesh = mesh

        def stress_free(self, theta):
            if self.mesh < 16.0:
                raise fem.ConvergenceError(f"load factor 0.{int(self.mesh)}")

    ref = SimpleNamespace(reference="r")
    work = SimpleNamespace(path="WORK", measurements=ref, record={"c1_pa": 423.4})
    params = {"mesh_size_mm": 14.0}
    spheres = ([((0.0, 0.0, 20.0), 12.0)], 4.0)
    then = next_mesh_sizes(params)
    assert then == [16.0, 18.0]
    fm, note, size, _, failed = _sized_model(work, params, Model, 14.0, spheres, then=then)
    assert failed == [(14.0, "load factor 0.14")]  # the refit's mesh.failed_sizes
    inner = "with its 1 inclusion 4 mm or wider meshed as spheres of 4 mm"
    assert fm.mesh == size == 16.0
    assert note == (
        f"no straight stress-free reference on a 14 mm model mesh {inner} at the "
        f"calibrated c1 (load factor 0.14); diagnosed on the 16 mm mesh {inner} (the "
        "calibration's: 14 mm)"
    )
    both = r"on a 12 mm model mesh .*\(load factor 0.12\) nor on a 14 mm one \(load factor 0.14\)"
    bounded = (
        r" nor on a 12 mm one \(with a 165 deg dihedral bound: load factor 0.12\) nor on a 14 mm"
        r" one \(with a 165 deg dihedral bound: load factor 0.14\); choose another --mesh-size"
    )  # the same sizes again with fewer slivers
    with pytest.raises(DiagnosisError, match=both + bounded):
        _sized_model(work, params, Model, 12.0, spheres, then=[14.0])
    with pytest.raises(DiagnosisError, match=r"on a 12 mm model mesh .*0.12\); choose"):
        _sized_model(work, params, Model, 12.0, spheres)  # asked for: never replaced
    with pytest.raises(DiagnosisError, match=r"inclusion_mesh_mm \(--inclusion-mesh\) must lie in"):
        DiagnosisOptions(inclusion_mesh_mm=0.5)


def test_inclusion_meshes_start_from_the_size_the_calibration_ran_on(monkeypatch):
    # build_problem's choice for --inclusion-mesh: without --mesh-size, the size the
    # calibration ran on (mesh.size_mm: 14 mm after 12 mm failed), then its next sizes
    # other than that one; with --mesh-size, that size alone (review P: it started from
    # the size asked for, 12 mm, and called it the calibration's)
    problem = importlib.import_module("calib.discrepancy.problem")

    class Chosen(Exception):
        pass

    asked = []

    def sized(work, params, model_on, size, spheres=None, *, then=(), say=None):
        asked.append((size, list(then), spheres[1]))
        raise Chosen

    monkeypatch.setattr(problem, "_sized_model", sized)
    monkeypatch.setattr(problem, "choose_scans", lambda work, holdout: (["a", "b"], None))
    monkeypatch.setattr(problem, "reference_inclusions", lambda work: [((0, 0, 20), 12.0)])
    record = {
        "c1_pa": 423.4,
        "model": {},
        "mesh": {"size_mm": 14.0},
        "provenance": {"parameters": {"mesh_size_mm": 12.0, "mesh_retry_mm": [14.0, 16.0]}},
    }
    work = SimpleNamespace(path="WORK", record=record)
    for kw in ({}, {"mesh_size_mm": 10.0}):
        with pytest.raises(Chosen):
            problem.build_problem(work, inclusion_mesh_mm=5.0, **kw)
    assert asked == [(14.0, [16.0], 5.0), (10.0, [], 5.0)]


def _gap_problem(same_mesh: bool):
    """A stand-in Problem whose posture solve puts every node at (c1, c1, c1) mm."""
    solved = []

    def solve(theta, values, names, gradient, nuisance):
        solved.append(round(float(np.exp(theta)), 6))
        return {n: SimpleNamespace(positions_mm=np.full((2, 3), np.exp(theta))) for n in names}

    work = SimpleNamespace(
        states={n: SimpleNamespace(positions_mm=np.zeros((2, 3)), tumour_mm=None)
                for n in ("a", "b", "h")},
        mesh=SimpleNamespace(faces=None), nipple_node=0,
    )  # fmt: skip
    prob = SimpleNamespace(
        scans=("a", "b"), holdout="h", solve=solve, work=work, same_mesh=same_mesh,
        sim=SimpleNamespace(faces=None), nipple_node=0, measurement=lambda n: n,
        residuals=lambda n, pos, nuisance=None: SimpleNamespace(r=pos[:, 0] + (nuisance or 0.0)),
        points=dict.fromkeys(("a", "b", "h")), weighted=lambda n, res, points: res,
    )  # fmt: skip
    return prob, solved


def _fit(c1_pa: float):
    return SimpleNamespace(theta=np.log(c1_pa), values=None, nuisance={})


def test_the_gap_compares_the_named_effect_on_one_mesh(monkeypatch):
    # The quick inclusions twin (seed 0) was diagnosed on 16 mm (its 14 mm calibration
    # has a prestressed reference) and nothing was named, yet the gap grew from 0.186 to
    # 0.224 mm on right lateral: before was the calibration on its own mesh. Before is
    # c1 alone on the diagnosis mesh now; the calibration's own errors are kept beside.
    import importlib

    import calib.model.residuals as residuals

    dg = importlib.import_module("calib.discrepancy.diagnose")

    def metrics(scan, positions_mm, faces, nipple, tumour):
        mean = float(positions_mm.mean())  # the stand-in's error: the solved c1 (exp ln c1)
        return SimpleNamespace(surface_error_mm={"fiducial": {"mean": mean}},
                               nipple_error_mm={"fiducial": mean})  # fmt: skip

    monkeypatch.setattr(dg, "scan_metrics", metrics)
    monkeypatch.setattr(residuals.SimulatedSurface, "of", staticmethod(lambda mesh: mesh))
    monkeypatch.setattr(
        residuals, "scan_residuals", lambda *a, **k: type("R", (), {"r": np.zeros(2)})
    )
    say = []
    null, final = _fit(430.0), _fit(415.0)

    prob, solved = _gap_problem(same_mesh=False)
    gaps, _ = dg._gaps(prob, null, final, say.append)
    # the final model, c1 alone on this mesh, then the final model again: the refit's
    # files take the forward model's last recovery (review AU: the null fit's was left)
    assert solved == [415.0, 430.0, 415.0]
    doc = gaps["h"].as_json(floor_mm=0.0)
    assert gaps["h"].role == "holdout"
    errors = {k: v["mean"] for k, v in doc["surface_error_mm"].items()}
    assert errors == pytest.approx({"before": 430.0, "after": 415.0, "calibration": 0.0})
    # the cut is measured on the residuals to the curved surface (the floor's quantity)
    assert doc["residual_mm"]["before"]["mean"] == pytest.approx(430.0)
    assert doc["residual_mm"]["after"]["rms"] == pytest.approx(415.0)
    assert doc["cut_above_floor"] == pytest.approx(15.0 / 430.0)
    assert gaps["h"].as_json(floor_mm=400.0)["cut_above_floor"] == pytest.approx(15.0 / 30.0)
    assert any("c1 alone on the diagnosis mesh" in s for s in say)

    # a named rigid offset moves its scan's points in the gap's residuals, as in the fit
    # (the stand-in's offset adds to the residual)
    moved = SimpleNamespace(theta=np.log(415.0), values=None, nuisance={"a": 2.0})
    gaps, _ = dg._gaps(_gap_problem(same_mesh=False)[0], null, moved, say.append)
    assert gaps["a"].as_json(0.0)["residual_mm"]["after"]["mean"] == pytest.approx(417.0)
    assert gaps["b"].as_json(0.0)["residual_mm"]["after"]["mean"] == pytest.approx(415.0)

    prob, solved = _gap_problem(same_mesh=False)
    gaps, _ = dg._gaps(prob, null, null, say.append)  # nothing named: before is after
    assert solved == [430.0]
    assert gaps["a"].as_json(0.0)["cut_above_floor"] == 0.0
    # and the diagnosis reports no cut then: "after" is c1 alone refitted, not an effect
    assert gaps["a"].as_json(0.0, named=False)["cut_above_floor"] is None

    prob, solved = _gap_problem(same_mesh=True)  # on its own mesh: before is the calibration
    gaps, _ = dg._gaps(prob, null, final, say.append)
    assert solved == [415.0]
    doc = gaps["a"].as_json(floor_mm=0.0)
    assert doc["surface_error_mm"]["before"] == {"mean": 0.0}
    assert "calibration" not in doc["surface_error_mm"]


def test_physical_effects_take_the_candidate_places_before_nuisances():
    # Quick poisson twin, seed 0 (nu 0.45): registration, sliding and poisson screened
    # significant in that order. Two places (max_candidates): the strongest physical
    # effects, sliding and poisson (the hidden one, Holm p = 3e-4), plus a confounded
    # partner; the nuisance waits for its stage.
    from calib.discrepancy.diagnose import _candidates

    sig = [("registration", 6.1, 1e-4), ("sliding", 5.9, 2e-4), ("poisson", 5.6, 3e-4),
           ("skin", 4.0, 0.01), ("inclusions", 3.0, 0.02)]  # fmt: skip
    o = DiagnosisOptions()

    def cosine(a, b):
        return 0.95 if {a, b} == {"poisson", "inclusions"} else 0.1

    # physical effects first (inclusions: confounded with poisson), the nuisance after
    assert _candidates(sig, cosine, o) == [["sliding", "poisson", "inclusions"], ["registration"]]
    assert _candidates(sig, lambda a, b: 0.0, o) == [["sliding", "poisson"], ["registration"]]


def test_nuisances_are_refitted_only_when_no_physical_effect_passes():
    # Quick inclusions twin, seed 2 (its screening's |t| and Holm-across-effects p):
    # inclusions and the right lateral's gravity angle and rigid offset are significant,
    # the nuisances stronger. A per-scan nuisance can absorb one posture's print of a
    # physical effect; it is the fallback.
    from calib.discrepancy.diagnose import _candidates

    sig = [("gravity", 4.11, 0.014), ("registration", 4.11, 0.028), ("inclusions", 3.11, 0.028)]
    stages = _candidates(sig, lambda a, b: 0.0, DiagnosisOptions())
    assert stages == [["inclusions"], ["gravity", "registration"]]
    stages = _candidates(sig[:2], lambda a, b: 0.0, DiagnosisOptions())
    assert stages == [[], ["gravity", "registration"]]


def _sphere(radius_mm: float, resolution: int):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius_mm, resolution=resolution)
    return np.asarray(m.vertices, float), np.asarray(m.triangles, np.int64)


def test_the_curved_surface_carries_the_chord_gap_with_the_material():
    # Closed form: a coarse sphere's facets lie inside the sphere by up to the sagitta;
    # points of the true sphere moved rigidly with the coarse one are at zero distance
    # from the curved surface (the gap is carried with the material), not from the facets.
    from scipy.spatial.transform import Rotation

    from calib.model.residuals import SimulatedSurface, _surface

    R = 50.0
    coarse, faces = _sphere(R, 20)  # edges up to ~ 16 mm, as a quick model mesh
    fine, fine_faces = _sphere(R, 200)  # edges up to ~ 1.6 mm
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    on_sphere = R * d / np.linalg.norm(d, axis=1, keepdims=True)
    rot = Rotation.from_rotvec([0.3, -0.2, 0.5])
    move = np.array([10.0, -4.0, 7.0])
    pos, points = rot.apply(coarse) + move, rot.apply(on_sphere) + move

    straight = SimulatedSurface(faces)
    curved = straight.curved(coarse, fine, fine_faces)
    raw = _surface(straight, pos, None, points).r
    r = _surface(curved, pos, None, points).r
    assert raw.mean() > 0.1  # the facets lie inside: positive distances of the true points
    # Tolerance: the fine sphere's own sagitta h^2 / (8 R), plus the first-order
    # correction's neglect: the gap is measured along the reference facet's normal, the
    # sphere's normal is tilted from it by up to theta ~ h / R, so gap * theta^2 / 2.
    h, h_fine = 2 * np.pi * R / 20, 2 * np.pi * R / 200
    tol = h_fine**2 / (8 * R) + raw.max() * (h / R) ** 2 / 2
    assert np.abs(r).max() < tol < 0.2 * raw.mean()
    # the derivative is that of the straight facet (the gap is fixed to the material)
    dpos = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    dr_curved = _surface(curved, pos, dpos, points).dr
    assert np.allclose(dr_curved, _surface(straight, pos, dpos, points).dr)


def test_the_facet_gap_at_the_scanned_points_is_their_distance_inside_the_facets():
    # Closed form: at a coarse sphere's own points (at rest, no motion) the gap of the
    # nearest facet point is minus the point's distance from the facets, and it lies in
    # [-sagitta, 0]: a facet of edge h cuts the sphere's chord by up to h^2 / (8 R).
    from calib.model.residuals import SimulatedSurface, _surface

    R = 50.0
    coarse, faces = _sphere(R, 20)
    fine, fine_faces = _sphere(R, 200)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(500, 3))
    points = R * d / np.linalg.norm(d, axis=1, keepdims=True)
    straight = SimulatedSurface(faces)
    curved = straight.curved(coarse, fine, fine_faces)
    raw = _surface(straight, coarse, None, points).r
    gap = curved.gap_at(points)
    # Tolerance: the fine sphere's own sagitta and the tilt of the facet's normal from
    # the sphere's (as in the test above)
    h, h_fine = 2 * np.pi * R / 20, 2 * np.pi * R / 200
    tol = h_fine**2 / (8 * R) + raw.max() * (h / R) ** 2 / 2
    assert np.abs(gap + raw).max() < tol
    assert gap.max() < tol and gap.min() > -(h**2) / (8 * R) - tol
    assert np.all(straight.gap_at(points) == 0.0)  # straight facets carry no gap


def test_options_take_one_effect_name_and_refuse_a_number_as_text():
    # review AU: "skin" was read letter by letter, alpha="0.05" a bare TypeError
    assert DiagnosisOptions(effects="skin").effects == ("skin",)
    assert DiagnosisOptions(effects=["skin", "poisson"]).effects == ("skin", "poisson")
    with pytest.raises(DiagnosisError, match=r"alpha \(--alpha\) must be a number, got '0.05'"):
        DiagnosisOptions(alpha="0.05")
    with pytest.raises(DiagnosisError, match=r"mesh_size_mm \(--mesh-size\) must be a number"):
        DiagnosisOptions(mesh_size_mm="12")


def test_points_at_the_clamped_rim_are_left_out(caplog):
    from calib.discrepancy.problem import RIM_MARGIN_MM, _off_the_rim, rim_margin_of

    z = np.linspace(0.0, 40.0, 81)  # heights above the back plate, mm
    pts = np.column_stack([np.zeros_like(z), np.ones_like(z), z])
    scan = SimpleNamespace(
        name="tilt_50",
        back_point_mm=np.array([3.0, -2.0, 0.0]),
        back_normal=np.array([0.0, 0.0, -1.0]),  # the side the normal points to is no matter
        surface_points=lambda max_points, seed: pts,
    )
    kept, within = _off_the_rim(scan, 100, 0, 5.0)
    assert np.array_equal(kept, pts[z >= 5.0]) and np.array_equal(within, pts[z < 5.0])
    kept, within = _off_the_rim(scan, 100, 0, 0.0)
    assert np.array_equal(kept, pts) and len(within) == 0
    with pytest.raises(DiagnosisError, match=r"tilt_50: only 21 of 81 .* rim margin \(30 mm\)"):
        _off_the_rim(scan, 100, 0, 30.0)
    with pytest.raises(DiagnosisError, match="rim_margin_mm"):
        DiagnosisOptions(rim_margin_mm=-1.0)
    # review W: 5 mm slices across the plate blur the junction past a 5 mm margin: said
    # (the twin's at most 1.5 mm slices are not)
    for depth, said in ((1.5, False), (5.0, True)):
        scan.back_voxel_depth_mm = depth
        caplog.clear()
        with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
            _off_the_rim(scan, 100, 0, 5.0)
        assert ("--rim-margin 7 leaves it out" in caplog.text) is said
    # "element" leaves out one model element, never less than the extraction's blur; a
    # width is taken as it is
    assert rim_margin_of(14.0, "element") == 14.0 and rim_margin_of(14.0, 3.0) == 3.0
    assert rim_margin_of(4.0, "element") == RIM_MARGIN_MM == 5.0
    assert rim_margin_of(14.0) == 5.0 and rim_margin_of(14.0, 0.0) == 0.0
    with pytest.raises(DiagnosisError, match="'elements'"):
        rim_margin_of(14.0, "elements")
    assert DiagnosisOptions(rim_margin_mm="element").rim_margin_mm == "element"
    with pytest.raises(DiagnosisError, match="rim_margin_mm"):
        DiagnosisOptions(rim_margin_mm="one")


def test_the_gap_figure_says_what_after_adds():
    from calib.report.diagnosis import gap_figure

    summary = {"mean": 0.2, "rms": 0.25, "p95": 0.4, "n": 10}
    gap = {
        n: {"role": role, "residual_mm": {"before": summary, "after": summary | {"mean": 0.1}}}
        for n, role in (("right_lateral", "diagnosis"), ("tilt_25", "holdout"))
    }
    ax = gap_figure(gap, 0.05, ("skin",)).axes[0]
    assert ax.get_title() == "the gap before and after adding skin"
    before, after = ax.containers
    assert [b.get_height() for b in before] == [0.2, 0.2]
    assert [b.get_height() for b in after] == [0.1, 0.1]
    assert after[1].get_hatch() == "//" and after[0].get_hatch() is None  # the holdout
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "with skin (after)" in legend and "hatched: held out (never fitted)" in legend
    plain = gap_figure(gap, 0.05).axes[0]
    assert plain.get_title().startswith("nothing named")
    # review BY, F5: nothing was added, so "after" is c1 re-fitted, not a "final model"
    assert "c1 re-fitted (after)" in [t.get_text() for t in plain.get_legend().get_texts()]


def test_the_localisation_map_shows_the_maps_flank_and_says_it_saturates():
    # review BY: the side panel drew the +y points over the -y ones (the surface maps show
    # the -y flank: a view from -y), and |z| beyond the scale's 4 looked like 4
    from types import SimpleNamespace

    from calib.report.diagnosis import Z_LIMIT, localisation_figure

    rng = np.random.default_rng(0)
    u = rng.normal(size=(400, 3))
    points = 30.0 * u / np.linalg.norm(u, axis=1)[:, None]  # a sphere
    z = np.where(points[:, 1] < 0, 6.0, -1.0)  # the -y flank far out, the +y one not
    region = SimpleNamespace(region="rim", z=6.0, mean_mm=0.3)
    m = SimpleNamespace(name="s", points_mm=points, z=z, regions=(region,), bandwidth_mm=8.0)
    fig = localisation_figure(m, np.eye(3))
    front, side = fig.axes[:2]
    assert (front.get_title(), side.get_title()) == (
        "front (from the apex)",
        "side (lateral, from -y)",
    )
    drawn = side.collections[0]
    last = drawn.get_offsets()[-50:]  # the points drawn last: the -y flank's
    on_top = np.isin(points[:, [0, 2]].round(9), np.asarray(last).round(9)).all(axis=1)
    assert np.all(points[on_top, 1] < 0)
    assert np.all(np.asarray(drawn.get_array())[-50:] == 6.0)
    assert drawn.colorbar.ax.get_ylabel().startswith(
        "local z of the smoothed residual (largest |z| 6.0)"
    )
    assert max(abs(z)) > Z_LIMIT and drawn.colorbar.extend == "both"


def test_an_unexplained_verdict_from_nuisances_alone_says_what_to_try():
    from calib.report.diagnosis import nuisance_only_hint

    kinds = {"skin": "material", "gravity": "nuisance", "registration": "nuisance"}
    names = ("skin", "gravity[right_lateral].a0", "registration[tilt_50].tx")

    def doc(verdict, significant):
        # as diagnosis.json: an effect is significant where one of its columns is
        cols = [{"name": n, "significant": n in significant} for n in names]
        hit = {n.split("[")[0] for n in significant}
        effects = {e: {"kind": k, "significant": e in hit} for e, k in kinds.items()}
        return {"verdict": verdict, "effects": effects, "screening": {"columns": cols}}

    hint = nuisance_only_hint(doc("unexplained", {"gravity[right_lateral].a0"}))
    assert "gravity on right_lateral" in hint and "--mesh-size" in hint
    both = nuisance_only_hint(
        doc("unexplained", {"gravity[right_lateral].a0", "registration[tilt_50].tx"})
    )
    assert "(gravity, registration on right_lateral, tilt_50)" in both
    # a physical effect among them, nothing significant, or a named effect: no hint
    assert nuisance_only_hint(doc("unexplained", {"skin", "gravity[right_lateral].a0"})) == ""
    assert nuisance_only_hint(doc("unexplained", set())) == ""
    assert nuisance_only_hint(doc("named: skin", {"gravity[right_lateral].a0"})) == ""


def test_the_summary_says_what_size_the_effects_not_found_would_need():
    from calib.report.diagnosis import detection_limits

    unit = "skin c1 / bulk c1 - 1"
    effects = {
        "skin": {
            "kind": "material",
            "significant": False,
            "detectable": 0.512,
            "screen_unit": unit,
        },
        "poisson": {"kind": "material", "significant": True, "detectable": 0.02},
        "density": {"kind": "scaling", "significant": False, "detectable": None},
        "gravity": {"kind": "nuisance", "significant": False, "detectable": None},
    }
    text = detection_limits({"effects": effects})
    # only the physical effect that was screened and not found, in its column's units
    assert text.endswith("skin 0.512 (skin c1 / bulk c1 - 1)"), text
    assert "poisson" not in text and "density" not in text and "gravity" not in text
    effects["skin"]["significant"] = True
    assert detection_limits({"effects": effects}) == ""


def test_the_sliding_probe_is_sized_by_the_body():
    # closed form: 70 x 2 c1 / H rounded to a power of ten. The demo's calibration (551.9
    # Pa, its reference surface 74.5 mm above the plate) and the twin's truth (420 Pa)
    # keep the 1000 Pa/mm every README figure was measured with; a soft tall body and a
    # stiff flat one get probes a decade softer and stiffer, and the sliding limit's
    # quantity and its refit's bounds follow (the probe was 1000 Pa/mm for every body)
    import math

    from calib.discrepancy.limits import _s_max, _value, _values_at
    from calib.discrepancy.problem import Problem, sliding_probe_pa_per_mm

    cases = {(551.9, 74.5): 1000.0, (420.0, 74.5): 1000.0, (100.0, 150.0): 100.0}
    cases[(2000.0, 40.0)] = 10000.0
    for (c1, height), probe in cases.items():
        assert sliding_probe_pa_per_mm(c1, height) == pytest.approx(probe, rel=1e-12)
        prob = Problem(
            work=None,
            fm=None,
            base=None,
            sim=None,
            points={},
            centres={},
            scans=[],
            holdout=None,
            theta_calibrated=math.log(c1),
            inclusions=[],
            skin_thickness_mm=1.5,
            body_height_mm=height,
        )
        assert prob.sliding_probe_pa_per_mm == pytest.approx(probe, rel=1e-12)
        # one probe amplitude is the probe's springs; the softest end is the refit's bound
        assert _value("sliding", 1.0, 0.499, probe) == probe
        soft = _values_at("sliding", EffectValues(), _s_max("sliding", 0.499), probe)
        assert math.log(soft.support_stiffness_pa_per_mm) == pytest.approx(
            sliding_ln_k_bounds(probe)[0], rel=1e-12
        )
    for c1, height in ((420.0, 0.0), (0.0, 74.5), (math.nan, 74.5)):
        with pytest.raises(DiagnosisError, match="sliding probe needs a positive c1"):
            sliding_probe_pa_per_mm(c1, height)


def test_the_sliding_entry_records_its_probe_also_where_it_could_not_run():
    # the 1.4x twin: the probe had no FE solution, and diagnosis.json did not say which
    # probe (its entry records it only where the screen ran)
    import importlib

    dg = importlib.import_module("calib.discrepancy.diagnose")
    fake = SimpleNamespace(
        options=SimpleNamespace(effects=("sliding", "skin")),
        screen=SimpleNamespace(screening=None),
        unavailable={"sliding": "no FE solution with the sliding probe"},
        problem=SimpleNamespace(sliding_probe_pa_per_mm=1000.0, body_height_mm=103.7),
        limits={},
    )
    out = dg.Diagnosis.effect_summary(fake)
    assert out["sliding"]["status"] == "unavailable"
    assert (out["sliding"]["probe_pa_per_mm"], out["sliding"]["body_height_mm"]) == (1000.0, 103.7)
    assert "probe_pa_per_mm" not in out["skin"]


def test_a_sliding_plate_is_refitted_as_ln_k_of_its_springs():
    # the refit's parameter layout: ln k from 1/100 to 1000 times the screen's probe (the
    # twins' 10 to 1e6 Pa/mm with their 1000 Pa/mm probe; a softer body's range moves
    # with its probe), and the model it unpacks holds the plate on springs of that
    # stiffness (fem.Sliding, rim held)
    import math

    from calib.discrepancy.refit import _layout, unpack_parameters
    from calib.model.effects import effect_support

    for probe, (k_lo, k_hi) in ((1000.0, (10.0, 1e6)), (100.0, (1.0, 1e5))):
        prob = SimpleNamespace(scans=SCANS, sliding_probe_pa_per_mm=probe)
        names, lo, hi = _layout(prob, ("sliding",), math.log(420.0))
        assert names == ("theta", "sliding")
        assert (lo[1], hi[1]) == sliding_ln_k_bounds(probe)
        assert (lo[1], hi[1]) == pytest.approx((math.log(k_lo), math.log(k_hi)), rel=1e-12)
    x = np.array([math.log(420.0), math.log(250.0)])
    theta, values, _ = unpack_parameters(prob, names, x, EffectValues())
    assert values.support == "springs"
    assert effect_support(values).tangent_stiffness_pa_per_mm == pytest.approx(250.0)


def test_refit_parameters_are_said_in_their_quantity_and_unit():
    # review AX: the refit's lines said "skin = 6.868" (ratio - 1), "gravity[...].a0 =
    # 0.01221" (rad) and "registration[...].ty = -0.9021" (mm) without a unit; each
    # parameter is said as the quantity it stands for, its interval converted the same way
    # (a monotone map, so the interval's ends are the ends' images)
    import math

    from calib.discrepancy.refit import parameter_text
    from calib.report.diagnosis import format_diagnosis

    said = {
        ("theta", math.log(422.0)): "c1 = 422.0 Pa",
        ("skin", 6.868): "skin ratio = 7.868",
        ("inclusions", 4.0): "inclusions ratio = 5",
        ("sliding", math.log(311.0)): "sliding springs = 311 Pa/mm",
        ("mooney", 0.5): "mooney c2/c1 = 0.5",
        ("poisson", 0.45): "poisson nu = 0.45",
        ("gravity[tilt_25].a1", math.radians(0.7)): "gravity[tilt_25].a1 = 0.7 deg",
        ("registration[tilt_25].ty", -0.9021): "registration[tilt_25].ty = -0.902 mm",
        ("registration[tilt_25].wz", math.radians(-1.5)): "registration[tilt_25].wz = -1.5 deg",
    }
    for (name, value), text in said.items():
        assert parameter_text(name, value) == text
    assert parameter_text("sliding", math.log(300.0), (math.log(250.0), math.log(400.0))) == (
        "sliding springs = 300 Pa/mm (95 % 250 - 400 Pa/mm)"
    )
    # the command's summary says a named effect's interval in the same words
    doc = {
        "verdict": "named: skin",
        "named": ["skin"],
        "calibration": {"c1_pa": 554.5},
        "c1_pa": 422.0,
        "refit": {"intervals": {"skin": {"value": 6.868, "ci95": [5.327, 8.409]}}},
        "gap": {},
        "noise": {"floor_mean_abs_mm": 0.079},
        "scans": {"diagnosis": ["right_lateral", "tilt_50"], "holdout": None},
        "effects": {},
        "model_mesh": {},
    }
    assert "\nskin ratio = 7.868 (95 % 6.327 - 9.409)\n" in format_diagnosis(doc)
    # review BC: a Wald interval cut to the values the model admits is said in the same
    # quantity as the cut one beside it (its note said the ratio - 1, "(-133 - 190)")
    doc["named"], doc["verdict"] = ["inclusions"], "named: inclusions"
    cut = {"value": 28.3, "ci95": [-0.999, 190.0], "ci95_unclipped": [-133.0, 190.0]}
    doc["refit"]["intervals"] = {"inclusions": cut}
    said = format_diagnosis(doc)
    assert "\ninclusions ratio = 29.3 (95 % 0.001 - 191)\n" in said
    assert "\n  its 95 % interval, inclusions ratio from -132 to 191, is cut" in said


def test_the_summary_says_what_the_verdict_does_not_rest_on():
    # review BO: effects not tested (no inclusions found, a probe without an FE solution),
    # no scan held out, and a single scan fitted were said in the HTML report or the log
    # only, beside a bare "no missing effect"
    from calib.report.diagnosis import format_diagnosis

    doc = {
        "verdict": "no missing effect",
        "named": [],
        "calibration": {"c1_pa": 420.0},
        "c1_pa": 420.0,
        "refit": {"intervals": {}},
        "gap": {},
        "noise": {"floor_mean_abs_mm": 0.079},
        "scans": {"diagnosis": ["right_lateral", "tilt_25"], "holdout": "tilt_50"},
        "effects": {},
        "model_mesh": {},
        "unavailable": {},
    }
    plain = format_diagnosis(doc)
    assert "not tested" not in plain and "held out" not in plain and "single scan" not in plain
    doc["unavailable"] = {"inclusions": "ingest found none", "sliding": "no FE solution"}
    doc["scans"] = {"diagnosis": ["right_lateral"], "holdout": None}
    said = format_diagnosis(doc)
    assert (
        "not tested, so not part of the verdict: inclusions (ingest found none); sliding "
        "(no FE solution)"
    ) in said
    assert "a single scan fitted (right_lateral): leave-one-posture-out cannot run" in said
    assert "no scan held out" in said


def test_the_console_says_the_leave_one_posture_out_rule_as_judged():
    # review BC: a nuisance passes leave-one-posture-out where its prediction is not worse
    # (_judge: la <= lb), a physical effect where it is better; the line said "better" of both
    from calib.discrepancy.diagnose import _lopo_word

    said = {
        (effect, ok): _lopo_word(SimpleNamespace(effect=effect, lopo_improves=ok))
        for effect in ("skin", "registration")
        for ok in (True, False)
    }
    assert said == {
        ("skin", True): "better",
        ("skin", False): "not better",
        ("registration", True): "not worse",
        ("registration", False): "worse",
    }


def test_the_registration_tolerance_takes_half_the_largest_voxel_edge(tmp_path):
    # closed form: 3 x the larger expected TRE + half the largest voxel edge (thick
    # slices place a point to half a slice along their axis; the twin is isotropic)
    import json

    from calib.discrepancy.problem import _registration_tolerance

    scan = tmp_path / "scans" / "a"
    scan.mkdir(parents=True)
    doc = {"tre_nipple_mm": 0.1, "tre_tumour_mm": 0.2, "voxel_size_mm": [1.0, 1.0, 3.0]}
    (scan / "ingest.json").write_text(json.dumps(doc))
    work = SimpleNamespace(path=tmp_path)
    assert _registration_tolerance(work, "a") == pytest.approx(3.0 * 0.2 + 1.5)


def test_a_rigid_offset_may_reach_twice_its_scans_registration_tolerance():
    # a plausible offset moves no point by more than the scan's tolerance (3 x TRE + half
    # a voxel); with a large TRE the fixed 3 mm bound stopped it first ("at a bound")
    import math

    from calib.discrepancy.refit import _layout

    tol = {SCANS[0]: 0.87, SCANS[1]: 2.5}  # the twin's; a scan with a 0.6 mm TRE
    prob = SimpleNamespace(scans=SCANS, registration_tolerance_mm=tol)
    names, lo, hi = _layout(prob, ("registration",), math.log(420.0))
    bound = dict(zip(names, hi, strict=True))
    assert [bound[f"registration[{SCANS[0]}].{c}"] for c in ("tx", "ty", "tz")] == [3.0] * 3
    assert [bound[f"registration[{SCANS[1]}].{c}"] for c in ("tx", "ty", "tz")] == [5.0] * 3
    assert bound[f"registration[{SCANS[1]}].wx"] == pytest.approx(math.radians(2.0))
    assert np.array_equal(lo[1:], -hi[1:])


def test_rim_points_are_moved_by_the_scan_offset_like_the_diagnosed_ones(monkeypatch):
    # the localisation maps the band within the rim margin at the null fit: those points
    # take the scan's rigid offset about the diagnosed points' centre, as the fit's do
    import calib.discrepancy.problem as problem

    seen = []

    def residuals(*args, surface_points_mm):
        seen.append(surface_points_mm)
        return SimpleNamespace(r=surface_points_mm[:, 2])

    monkeypatch.setattr(problem, "scan_residuals", residuals)
    rng = np.random.default_rng(0)
    pts, rim = rng.normal(size=(20, 3)) * 30.0, rng.normal(size=(5, 3)) * 30.0
    prob = problem.Problem(
        work=None,
        fm=SimpleNamespace(mesh=None),
        base=None,
        sim=None,
        points={"a": pts},
        centres={"a": pts.mean(axis=0)},
        scans=["a"],
        holdout=None,
        theta_calibrated=6.0,
        inclusions=[],
        skin_thickness_mm=1.5,
        rim_margin_mm=14.0,
        rim_points={"a": rim},
    )
    prob.measurement = lambda name: None
    offset = np.array([0.5, -0.2, 0.1, 0.01, -0.02, 0.005])  # mm, rad
    nz = problem.Nuisance(offset=offset, gravity_rad=np.zeros(2))
    both = np.vstack([pts, rim])
    moved = problem._rigid(both, offset, pts.mean(axis=0))  # one rigid motion for all
    prob.residuals("a", None, None, nz)
    prob.residuals("a", None, None, nz, points_mm=rim)
    assert np.allclose(seen[0], moved[:20]) and np.allclose(seen[1], moved[20:])
    prob.residuals("a", None, None, None, points_mm=rim)
    assert seen[2] is rim


def test_a_noise_profile_weights_each_residual_by_its_measured_height(monkeypatch):
    # --noise-profile plate: residual and derivative of a point are divided by the relative
    # spread at its height above the plate; a rigid offset moves the point, not its weight
    import calib.discrepancy.problem as problem
    from calib.model.residuals import Residuals
    from calib.stats import HeightProfile

    monkeypatch.setattr(problem, "scan_residuals", lambda *a, surface_points_mm: Residuals(
        np.ones(len(surface_points_mm)), np.full(len(surface_points_mm), 2.0),
        surface_points_mm))  # fmt: skip
    pts = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 6.0], [0.0, 0.0, 40.0], [5.0, 0.0, 4.9]])
    prof = HeightProfile((0.0, 5.0, 30.0, np.inf), (4.0, 2.0, 1.0), (10, 10, 10), 0.1)
    prob = problem.Problem(
        work=None, fm=SimpleNamespace(mesh=None), base=None, sim=None, points={"a": pts},
        centres={"a": pts.mean(axis=0)}, scans=["a"], holdout=None, theta_calibrated=6.0,
        inclusions=[], skin_thickness_mm=1.5, profile=prof,
    )  # fmt: skip
    prob.measurement = lambda name: SimpleNamespace(
        back_point_mm=np.zeros(3), back_normal=np.array([0.0, 0.0, -1.0])
    )
    w = np.array([0.25, 0.5, 1.0, 0.25])
    res = prob.residuals("a", None, np.zeros((1, 3)))
    assert np.allclose(res.r, w) and np.allclose(res.dr, 2.0 * w)
    nz = problem.Nuisance(offset=np.array([0.0, 0.0, 3.0, 0.0, 0.0, 0.0]), gravity_rad=np.zeros(2))
    moved = prob.residuals("a", None, None, nz)
    assert np.allclose(moved.points_mm[:, 2], pts[:, 2] + 3.0)
    assert np.allclose(moved.r, w)  # the weights of the measured places
    rim = np.array([[0.0, 0.0, 0.5]])
    assert prob.residuals("a", None, points_mm=rim).r.tolist() == [0.25]
    flat = replace(prob, profile=None)
    flat.measurement = prob.measurement
    assert np.allclose(flat.residuals("a", None).r, 1.0)


def test_the_noise_profile_option_is_checked():
    assert DiagnosisOptions().noise_profile == "flat"
    with pytest.raises(DiagnosisError, match=r"noise_profile \(--noise-profile\) must be one of"):
        DiagnosisOptions(noise_profile="wavy")
    # the command refuses it before reading WORK (tests/calib/test_calib_cli.py lists the
    # choices of every command's choice options)


def test_the_mesh_error_option_is_checked():
    assert DiagnosisOptions().mesh_error == "ignored"
    with pytest.raises(DiagnosisError, match=r"mesh_error \(--mesh-error\) must be one of"):
        DiagnosisOptions(mesh_error="corrected")


def _wall_problem(monkeypatch, wall_c1_pa: float | None):
    """A stand-in Problem: r = ln c1 - ln 380 at every point, no FE solution below a wall."""
    import math

    import fem
    from calib.discrepancy import refit as rf

    def solve(theta, values, names, gradient, nuisance):
        if wall_c1_pa is not None and theta < math.log(wall_c1_pa):
            raise fem.ConvergenceError(f"no solution at {math.exp(theta):.1f} Pa")
        return {n: SimpleNamespace(positions_mm=np.full(4, theta - math.log(380.0))) for n in names}

    def fields(prob, theta, values, columns, nuisance, say):
        res = {n: s.positions_mm for n, s in solve(theta, values, prob.scans, False, None).items()}
        return FieldSet(prob.scans, res, {n: np.ones(4) for n in prob.scans}, (), {})

    monkeypatch.setattr(rf, "effect_fields", fields)
    return SimpleNamespace(
        scans=SCANS, theta_calibrated=math.log(420.0), base=SimpleNamespace(nu=0.499),
        solve=solve, residuals=lambda n, pos, weights, nuisance: SimpleNamespace(r=pos),
    )  # fmt: skip


def test_a_refit_whose_every_short_trial_has_no_fe_solution_does_not_claim_a_minimum(
    monkeypatch,
):
    # A linear residual whose least squares lies at 380 Pa. Without a wall the refit
    # lands there (one Gauss-Newton step is exact). With no FE solution below 419 Pa,
    # every trial from 420 Pa towards 380 fails down to 1/32 of the step (420 -> 418.7
    # Pa); before, the search then ended "no decrease along the step (a minimum within
    # the tolerance)" with success, and the diagnosis could name an effect on it.
    from calib.discrepancy.refit import refit

    free = refit(_wall_problem(monkeypatch, None), ())
    assert free.success and free.c1_pa == pytest.approx(380.0, rel=1e-9)

    walled = refit(_wall_problem(monkeypatch, 419.0), ())
    assert not walled.success
    assert "no FE solution along the step" in walled.message
    assert walled.c1_pa == pytest.approx(420.0)
    assert walled.failed_evaluations == 6  # t = 1, 1/2, ..., 1/32

    # a wall the short trials clear at first: the search walks up to it (420 -> 409.6 ->
    # 405.8 Pa) and ends when every trial beyond fails, unsuccessful as well
    lines = []
    near = refit(_wall_problem(monkeypatch, 405.0), (), say=lines.append)
    assert 405.0 <= near.c1_pa < 407.0
    assert not near.success and near.failed_evaluations > 0
    # each accepted step is numbered (two steps at one rounded c1 read as a repeated line)
    steps = [s for s in lines if "no FE solution" not in s]
    assert steps[0].startswith("  refit c1, step 1: c1 = 409.6 Pa, rms"), steps
    assert steps[1].startswith("  refit c1, step 2: c1 = 405.8 Pa"), steps


def _dome_problem(mesh_size_mm: float = 14.0):
    """Two scans of points on a 60 mm dome over a back plate at z = 0 (no FE)."""
    import calib.discrepancy.problem as problem

    rng = np.random.default_rng(5)
    pts = {}
    for n in ("a", "b"):
        u = rng.normal(size=(1200, 3))
        u[:, 2] = np.abs(u[:, 2])
        pts[n] = 60.0 * u / np.linalg.norm(u, axis=1)[:, None]
        pts[n] = pts[n][pts[n][:, 2] >= 5.0]  # the default rim margin, left out
    prob = problem.Problem(
        work=None,
        fm=SimpleNamespace(mesh=None),
        base=None,
        sim=None,
        points=pts,
        centres={n: p.mean(axis=0) for n, p in pts.items()},
        scans=["a", "b"],
        holdout=None,
        theta_calibrated=6.0,
        inclusions=[],
        skin_thickness_mm=1.5,
        rim_margin_mm=5.0,
        mesh_size_mm=mesh_size_mm,
        registration_tolerance_mm={"a": 1.0, "b": 1.0},  # 3 x TRE + half a 1.5 mm voxel
    )
    prob.measurement = lambda name: SimpleNamespace(
        back_point_mm=np.zeros(3), back_normal=np.array([0.0, 0.0, 1.0])
    )
    return prob, rng


def _fit_of(prob, residual: dict, columns: dict, x) -> Refit:
    """:func:`_refit` of per-scan residuals and columns at the dome's points."""
    from calib.discrepancy.screen import sample_of

    sample = sample_of(SimpleNamespace(scans=SCANS), prob.points)

    def cat(per_scan: dict) -> np.ndarray:
        return np.concatenate([per_scan[n] for n in SCANS])

    J = cat({n: prob.points[n][:, 2] / 60.0 for n in SCANS})  # a sag-like dr/d ln c1
    return _refit(sample, cat(residual), J, {k: cat(v) for k, v in columns.items()}, x)


def test_the_share_explained_is_judged_beyond_one_element_of_the_plate():
    # The clamped rim carries the model's own discretisation error (0.4 mm here, within one
    # 14 mm element of the plate), which no effect removes; the effect's print (0.15 mm
    # over the dome) is removed whole by its refit. Closed form: beyond the element the
    # refit explains var(print) / var(print) = 1 of the residual above the noise floor;
    # on every point the rim's 0.4^2 mm^2 over a fifth of them keeps the share below a half.
    from calib.discrepancy.diagnose import _explained, _judge, _judged_points

    prob, rng = _dome_problem()
    sigma = 0.05  # mm, the noise floor's sd
    margin, keep = _judged_points(prob, "element")
    h = {n: prob.points[n][:, 2] for n in prob.scans}
    assert margin == 14.0 and all(np.array_equal(keep[n], h[n] >= 14.0) for n in prob.scans)
    noise = {n: rng.normal(scale=sigma, size=len(h[n])) for n in prob.scans}
    rim = {}
    for n in prob.scans:  # +-0.4 mm within the element, in patches along x
        rim[n] = np.where(h[n] < 14.0, 0.4 * np.sign(np.sin(prob.points[n][:, 0])), 0.0)
    signal = {n: 0.15 * np.cos(prob.points[n][:, 0] / 15.0) for n in prob.scans}
    before = {n: rim[n] + signal[n] + noise[n] for n in prob.scans}
    after = {n: rim[n] + noise[n] for n in prob.scans}
    b = _fit_of(prob, before, {}, [6.0])
    col = {n: -signal[n] for n in prob.scans}
    a_phys = _fit_of(prob, after, {"inclusions": col}, [6.0, 1.0])
    floor = sigma**2
    off = _explained(b.fields, a_phys.fields, floor, keep)
    every = _explained(b.fields, a_phys.fields, floor, None)
    # sampling: the floor is the noise's true variance, the noise's own mean square over
    # ~1,600 points departs from it by ~3.5 % (sqrt(2 / n)), a share of ~0.2 % of the print's
    assert off == pytest.approx(1.0, abs=0.05)
    assert every < 0.4
    # _judge: a physical effect takes the larger of the two shares, a nuisance (the
    # explanation of last resort) the smaller; both shares are reported
    o = DiagnosisOptions()
    row = ("inclusions", 5.0, 1e-4)
    phys = _judge(prob, "inclusions", 1, row, b, a_phys, (floor, floor, keep), o)
    assert phys.explained == pytest.approx(off) and phys.explained_all_points == pytest.approx(
        every
    )
    assert "explains" not in phys.reason
    # an effect acting at the plate (a sliding plate) that removes the rim's misfit and
    # leaves the print: nothing beyond the element, most of it on every point; a physical
    # effect passes on either set of points
    at_rim = {n: signal[n] + noise[n] for n in prob.scans}
    a_rim = _fit_of(prob, at_rim, {"sliding": {n: -rim[n] for n in prob.scans}}, [6.0, 1.0])
    rim_off = _explained(b.fields, a_rim.fields, floor, keep)
    rim_all = _explained(b.fields, a_rim.fields, floor, None)
    assert abs(rim_off) < 0.05 and rim_all > 0.6
    slid = _judge(prob, "sliding", 1, ("sliding", 5.0, 1e-4), b, a_rim, (floor, floor, keep), o)
    assert slid.explained == pytest.approx(rim_all)
    # review BO: one that removes the rim's misfit but leaves the print 20 % larger beyond
    # the element (its mean square (1.2^2 - 1) = 0.44 of the excess worse, closed form
    # but for the noise's sampling) is not named, for any physical effect, though it
    # explains more than half on every point
    worse = {n: 1.2 * signal[n] + noise[n] for n in prob.scans}
    for eff in ("sliding", "poisson"):
        a_bad = _fit_of(prob, worse, {eff: {n: -rim[n] for n in prob.scans}}, [6.0, 1.0])
        assert _explained(b.fields, a_bad.fields, floor, keep) == pytest.approx(-0.44, abs=0.1)
        assert _explained(b.fields, a_bad.fields, floor, None) > 0.5
        bad = _judge(prob, eff, 1, (eff, 5.0, 1e-4), b, a_bad, (floor, floor, keep), o)
        assert not bad.passes and "worsens the fit beyond the plate's element" in bad.reason
    a_nuis = _fit_of(prob, after, {"gravity[a].a0": col}, [6.0, 0.01])
    nuis = _judge(prob, "gravity", 1, ("gravity", 5.0, 1e-4), b, a_nuis, (floor, floor, keep), o)
    assert nuis.explained == pytest.approx(every) and "explains" in nuis.reason
    # a margin that leaves fewer than half a scan's points drops to the smallest median
    # height (said and recorded); 0 or the rim margin judges every diagnosed point
    margin, keep = _judged_points(prob, 50.0)
    med = min(float(np.median(h[n])) for n in prob.scans)
    assert margin == pytest.approx(med) and all(keep[n].mean() >= 0.5 for n in prob.scans)
    for m in (0.0, 5.0):
        assert all(k.all() for k in _judged_points(prob, m)[1].values())
    assert _explained(b.fields, a_phys.fields, floor, _judged_points(prob, 0.0)[1]) == every
    with pytest.raises(DiagnosisError, match="explained_margin_mm"):
        DiagnosisOptions(explained_margin_mm=-2.0)
    with pytest.raises(DiagnosisError, match="explained_margin_mm"):
        DiagnosisOptions(explained_margin_mm="two")


def test_sliding_springs_at_the_refit_s_softest_are_said_as_such():
    # review BO: the refit's softest springs (the probe / 100) are where the model stops
    # solving, not the end of the effect's range (a frictionless plate lies past them);
    # "at a bound of its physical range" said the wrong thing. The stiffest end is one.
    from dataclasses import replace

    from calib.discrepancy.diagnose import _judge
    from calib.discrepancy.refit import sliding_ln_k_bounds

    prob, rng = _dome_problem()
    prob.body_height_mm = 60.0  # the dome's
    lo, hi = sliding_ln_k_bounds(prob.sliding_probe_pa_per_mm)
    h = {n: prob.points[n][:, 2] for n in prob.scans}
    r = {n: 0.1 * np.cos(prob.points[n][:, 0] / 15.0) + rng.normal(scale=0.05, size=len(h[n]))
         for n in prob.scans}  # fmt: skip
    b = _fit_of(prob, r, {}, [6.0])
    o = DiagnosisOptions()
    said = {}
    for end in (lo, hi):
        a = _fit_of(prob, r, {"sliding": {n: 0 * h[n] for n in prob.scans}}, [6.0, end])
        a = replace(a, lower=np.array([-np.inf, lo]), upper=np.array([np.inf, hi]))
        row = ("sliding", 5.0, 1e-4)
        said[end] = _judge(prob, "sliding", 1, row, b, a, (0.0025, 0.0025, None), o).reason
    probe = prob.sliding_probe_pa_per_mm
    assert f"springs at the refit's softest, {probe / 100:.3g} Pa/mm" in said[lo]
    assert "physical range" not in said[lo]
    assert "parameter at a bound of its physical range (sliding)" in said[hi]
    # a skin at the top of its range: a thicker band, said (review BO); at the bottom, a
    # bound of the range
    for end, words in ((99.0, "--skin-thickness 3 widens"), (-0.9, "physical range (skin)")):
        a = _fit_of(prob, r, {"skin": {n: 0 * h[n] for n in prob.scans}}, [6.0, end])
        a = replace(a, lower=np.array([-np.inf, -0.9]), upper=np.array([np.inf, 99.0]))
        cand = _judge(prob, "skin", 1, ("skin", 5.0, 1e-4), b, a, (0.0025, 0.0025, None), o)
        assert words in cand.reason, cand.reason


def test_a_nuisance_beyond_the_registration_is_implausible():
    # closed form: the scan's points lie on a sphere of 50 mm about its centre and its
    # registration allows 0.5 mm, so a rigid offset may move them 0.5 mm and gravity may
    # turn by 0.5 / 50 = 0.01 rad (0.57 deg), the rotation that moves the farthest point
    # by the same 0.5 mm
    from calib.discrepancy.diagnose import _gravity_excess, _registration_excess
    from calib.discrepancy.problem import Nuisance

    rng = np.random.default_rng(0)
    u = rng.normal(size=(200, 3))
    centre = np.array([10.0, 20.0, 30.0])
    pts = 50.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + centre
    tolerance = {"a": 0.5}
    prob = SimpleNamespace(
        scans=["a"], points={"a": pts}, centres={"a": centre}, registration_tolerance_mm=tolerance
    )

    def fit(gravity=(0.0, 0.0), offset=(0.0,) * 6):
        return SimpleNamespace(nuisance={"a": Nuisance(np.array(gravity), np.array(offset))})

    assert _gravity_excess(prob, fit((0.006, 0.0079))) == []  # 0.00991 rad
    (msg,) = _gravity_excess(prob, fit((0.006, -0.0081)))  # 0.01008 rad
    assert "gravity turned 0.58 deg" in msg and "allows 0.57 deg" in msg
    assert _registration_excess(prob, fit(offset=(0.3, 0.0, 0.39, 0, 0, 0))) == []
    assert _registration_excess(prob, fit(offset=(0.3, 0.0, 0.41, 0, 0, 0)))


def test_the_influence_vector_is_the_screens_one_step_estimate(linear):
    # screen()'s estimate of each column is influence @ r (both build on one series
    # design: this checks how they are put together, sign and conditioning). Review CF-6:
    # what makes it the one-step estimate is checked apart: a linear unbiased estimate of
    # the column's size, with c1 and each scan's offset projected out, reads the column's
    # own field (-dr/dp) as size 1 and c1's field and each offset as 0 (rounding: 1e-12)
    from calib.discrepancy.screen import influence

    sample, J, cols, sampler = linear
    r = _at_fit(J, sampler.draw(np.random.default_rng(3))[:, 0])
    fields = _fields(sample, r, J, cols)
    s = screen(fields, _points(sample))
    for e in s.screening.effects:
        a = influence(fields, _points(sample), e.name)
        assert float(a @ r) == pytest.approx(e.estimate, rel=1e-9, abs=1e-12)
        assert float(a @ -cols[e.name]) == pytest.approx(1.0, abs=1e-12)
        nuisances = [J, *(np.where(sample.scan == k, 1.0, 0.0) for k in range(2))]
        assert np.abs([a @ f for f in nuisances]).max() < 1e-12


def _with_discretisation(fields: FieldSet, sample, shape: np.ndarray) -> FieldSet:
    """``fields`` with a model-mesh discretisation column of the given stacked shape."""
    from calib.discrepancy.fields import DISCRETISATION

    blocks = {n: idx for n, idx in zip(SCANS, sample.blocks, strict=True)}
    col = Column(
        DISCRETISATION, DISCRETISATION, None, "amplitude", {n: shape[blocks[n]] for n in SCANS}
    )
    return replace(fields, columns=(*fields.columns, col))


def test_the_model_mesh_s_own_error_is_projected_out_of_every_test(linear):
    # the residual carries a 'tilt'-shaped print (0.15 mm rms, 0.75 noise sd: found in
    # each of 5 draws without the column, test above). Where the model mesh's own error
    # has that shape (the discretisation column), 'tilt' lies in what every test projects
    # out: not identifiable, never significant, its one-step estimate blind to the print
    # (influence . shape = 0 to round-off, 1e-9 of its norm); the column itself is
    # conditioned on, not screened. A planted 'bump' (other shape) is still found.
    from calib.discrepancy.screen import influence

    sample, J, cols, sampler = linear
    tilt = misfit_pattern(sample, kind="tilt")
    rng = np.random.default_rng(8)
    for _ in range(5):
        r = _at_fit(J, sampler.draw(rng)[:, 0] + 0.15 * tilt)
        plain = screen(_fields(sample, r, J, cols), _points(sample))
        assert {e.name: e for e in plain.screening.effects}["tilt"].significant
        fields = _with_discretisation(_fields(sample, r, J, cols), sample, tilt)
        s = screen(fields, _points(sample))
        by = {e.name: e for e in s.screening.effects}
        assert set(by) == set(cols)
        assert not by["tilt"].identifiable and not any(e.significant for e in by.values())
    for name in ("p2", "bump"):
        a = influence(fields, _points(sample), name)
        assert abs(float(a @ tilt)) <= 1e-9 * np.linalg.norm(a) * np.linalg.norm(tilt)
    r = _at_fit(
        J, sampler.draw(rng)[:, 0] + 0.15 * tilt + 0.2 * misfit_pattern(sample, kind="bump")
    )
    s = screen(_with_discretisation(_fields(sample, r, J, cols), sample, tilt), _points(sample))
    assert {e.name: e for e in s.screening.effects}["bump"].significant


def absorbed_null_alarms(linear, draws: int) -> dict[str, list[bool]]:
    """Per seeded draw with the model mesh's error in it, the screen's family-wise alarm
    with that error ignored and absorbed (the test below; ``bench_rate_tests.py``)."""
    sample, J, cols, sampler = linear
    _, y, z = sample.points_mm.T
    other = y * z - np.mean(y * z)
    shape = misfit_pattern(sample, kind="tilt") + other / np.sqrt(np.mean(other**2))
    shape = shape / np.sqrt(np.mean(shape**2))
    rng = np.random.default_rng(12)
    fw = {"ignored": [], "absorbed": []}
    for _ in range(draws):
        r = _at_fit(J, sampler.draw(rng)[:, 0] + 0.2 * shape)
        fields = _fields(sample, r, J, cols)
        for how, f in (
            ("ignored", fields),
            ("absorbed", _with_discretisation(fields, sample, shape)),
        ):
            s = screen(f, _points(sample), alpha=0.05)
            fw[how].append(any(e.significant for e in s.screening.effects))
    return fw


def test_with_the_model_mesh_s_error_absorbed_the_false_positive_rate_is_held(linear):
    # the model mesh's own error in every draw (0.2 mm rms of a smooth shape that shares
    # half its direction with 'tilt'), the correlated noise of the test above, 300 seeded
    # draws: ignored, 'tilt' screens significant far above 5 % (the false namings the
    # column is for); absorbed, the family-wise rate is at most 5 % + 3 binomial se
    # (8.8 % on 300 draws: a rate of 10 % passes with probability 0.26; review CF-9: 100
    # draws and 11.5 % passed it with 0.70, and the name said "nominal" where only an
    # upper bound is checked; long run 2.55 %, `python benchmarks/bench_rate_tests.py
    # --only absorbed`). The column is given the exact shape: this checks the projection, not how
    # well a coarser mesh's change matches the model mesh's error (measured on twins,
    # docs/diagnose-evidence.md)
    fw = absorbed_null_alarms(linear, 300)
    bound = 0.05 + 3 * np.sqrt(0.05 * 0.95 / 300)
    assert np.mean(fw["ignored"]) > 0.5, np.mean(fw["ignored"])
    assert np.mean(fw["absorbed"]) <= bound, np.mean(fw["absorbed"])


def test_the_discretisation_field_is_the_coarser_mesh_s_residual_at_the_same_points():
    # the coarser problem's own points differ (another mesh, another sampling); the field
    # must be its residual at the model problem's points, at the null fit's c1, minus the
    # model's residual there: with a fake 'coarser model' whose residual is a known
    # function of the point and theta the field is that function minus the residual,
    # exactly.
    import calib.discrepancy.problem as problem
    from calib.discrepancy.fields import discretisation_field

    prob, _ = _dome_problem()
    prob.fm = SimpleNamespace(mesh=None, solves=3)
    prob.profile = SimpleNamespace(relative_sd=[2.0, 1.0])  # the model's noise profile
    asked = {}

    class Coarser(problem.Problem):
        def solve(self, theta, values, names, *, gradient, nuisance=None):
            asked.update(theta=theta, names=list(names), gradient=gradient, values=values)
            self.fm.solves += len(names)
            return {n: SimpleNamespace(positions_mm=theta) for n in names}

        def residuals(
            self, name, positions_mm, dpositions_mm=None, nuisance=None, *, points_mm=None
        ):
            # weighted and moved as the model's residuals are
            assert self.profile is prob.profile and self.centres is prob.centres
            return SimpleNamespace(r=positions_mm * self.points[name][:, 2] / 60.0)

    coarse = Coarser(**{f: getattr(prob, f) for f in problem.Problem.__dataclass_fields__})
    coarse = replace(
        coarse,
        points={n: p[:10] + 1.0 for n, p in prob.points.items()},
        fm=SimpleNamespace(solves=0),
        base="neutral",
        profile=None,  # its own state: another profile, other centres
        centres={n: np.zeros(3) for n in prob.points},
    )
    residual = {n: 0.01 * np.arange(len(p)) for n, p in prob.points.items()}
    d = discretisation_field(prob, coarse, 6.1, residual)
    assert asked == {"theta": 6.1, "names": ["a", "b"], "gradient": False, "values": "neutral"}
    for n, p in prob.points.items():
        np.testing.assert_array_equal(d[n], 6.1 * p[:, 2] / 60.0 - residual[n])
    assert prob.fm.solves == 5  # the coarser mesh's solves are counted


def test_a_coarser_mesh_without_a_model_is_said_and_the_diagnosis_goes_on(monkeypatch, caplog):
    diagnose = importlib.import_module("calib.discrepancy.diagnose")

    prob, _ = _dome_problem(12.0)

    def refuse(work, **kw):
        assert kw["mesh_size_mm"] == pytest.approx(16.8)  # COARSER_FACTOR x 12 mm
        raise DiagnosisError("no straight stress-free reference on a 16.8 mm mesh")

    monkeypatch.setattr(diagnose, "build_problem", refuse)
    null = SimpleNamespace(theta=6.0, fields=None)
    opts = DiagnosisOptions(mesh_error="absorbed")
    said = []
    with caplog.at_level("WARNING"):
        out, same, record = diagnose._absorb_mesh_error(None, prob, null, opts, said.append)
    assert out is prob and same is null and not prob.discretisation
    assert record["status"] == "unavailable" and "16.8 mm" in record["reason"]
    assert "not absorbed" in caplog.text and said[-1].startswith("  not absorbed: no model")


def test_an_absorbed_mesh_error_joins_the_null_fit_s_fields_and_is_recorded(monkeypatch):
    # the success path without FE: the coarser problem (1,000 tets against the model's
    # 2,744: an effective factor of 1.4) and its field come from fakes; the null fit's
    # fields gain exactly one column, the problem carries the field for later refits, and
    # the record says what was built (the body 60 mm tall: 3.6 elements of 16.8 mm)
    diagnose = importlib.import_module("calib.discrepancy.diagnose")
    prob, rng = _dome_problem(12.0)
    prob.fm = SimpleNamespace(mesh=SimpleNamespace(n_tets=2744), solves=0)
    prob.body_height_mm = 60.0
    coarse = SimpleNamespace(
        mesh=SimpleNamespace(n_tets=1000), mesh_max_dihedral_deg=165.0, mesh_note="a note"
    )
    monkeypatch.setattr(diagnose, "build_problem", lambda work, **kw: coarse)
    d = {n: rng.normal(size=len(p)) for n, p in prob.points.items()}
    monkeypatch.setattr(diagnose, "discretisation_field", lambda p, c, theta, r: d)
    residual = {n: np.zeros(len(p)) for n, p in prob.points.items()}
    null = _fit_of(prob, residual, {}, np.array([6.0]))
    opts = DiagnosisOptions(mesh_error="absorbed")
    out, fit, record = diagnose._absorb_mesh_error(None, prob, null, opts, lambda m: None)
    assert out.discretisation is d and fit.theta == null.theta
    assert [c.name for c in fit.fields.columns] == ["discretisation"]
    np.testing.assert_array_equal(
        fit.fields.matrix(["discretisation"])[:, 0], np.concatenate([d["a"], d["b"]])
    )
    assert record["status"] == "absorbed" and record["effective_factor"] == pytest.approx(1.4)
    assert record["elements_tall"] == pytest.approx(60.0 / 16.8)
    assert (record["max_dihedral_deg"], record["note"], record["n_tets"]) == (165.0, "a note", 1000)
    assert record["rms_mm"]["a"] == pytest.approx(np.sqrt(np.mean(d["a"] ** 2)))


def test_the_residual_s_amplitude_along_the_mesh_error_and_what_it_shares(linear):
    # a residual carrying the column once (amplitude 1: an error of order 2 coarsened 1.4x
    # gives 1.04) over the correlated noise: the one-step amplitude within 3 standard
    # errors of 1; the column built half from 'tilt' shares its direction with 'tilt'
    # (|cos| >= 0.5 after c1 and the offsets are projected out), little with 'bump'
    from calib.discrepancy.screen import mesh_error_check

    sample, J, cols, sampler = linear
    _, y, z = sample.points_mm.T
    other = y * z - np.mean(y * z)
    shape = misfit_pattern(sample, kind="tilt") + other / np.sqrt(np.mean(other**2))
    shape = 0.2 * shape / np.sqrt(np.mean(shape**2))
    r = _at_fit(J, sampler.draw(np.random.default_rng(4))[:, 0] + shape)
    fields = _with_discretisation(_fields(sample, r, J, cols), sample, shape)
    s = screen(fields, _points(sample))
    check = mesh_error_check(fields, _points(sample), s.noise)
    assert check.amplitude == pytest.approx(1.0, abs=3 * check.standard_error)
    assert check.statistic > 2.0
    assert check.shared["tilt"] >= 0.5 > check.shared["bump"]
    assert mesh_error_check(_fields(sample, r, J, cols), _points(sample), s.noise) is None


def test_the_summary_says_whether_the_model_mesh_s_error_was_absorbed():
    from calib.report.diagnosis import _mesh_error

    assert _mesh_error({"model_mesh": {"size_mm": 12.0, "error": None}}) == ""
    rec = {
        "status": "absorbed",
        "size_mm": 16.8,
        "n_tets": 1570,
        "factor": 1.4,
        "rms_mm": {"right_lateral": 0.247, "tilt_50": 0.119},
    }
    said = _mesh_error({"model_mesh": {"error": rec}})
    assert "16.8 mm mesh (1570 tets)" in said and "right_lateral 0.247 mm" in said
    # the residual's amplitude along it, read (the dissertation null seed 1's: -0.60 +- 0.09)
    rec |= {"amplitude": -0.60, "standard_error": 0.09, "statistic": -6.7, "shared": {"skin": 0.6}}
    said = _mesh_error({"model_mesh": {"error": rec}})
    assert "amplitude -0.60 +- 0.09 (t -6.7): the coarser mesh fits better" in said
    assert said.endswith("shares its direction with skin (|cos| 0.60)")
    rec |= {"amplitude": 1.1, "statistic": 5.0}
    assert "as the model mesh's error of a converging order" in _mesh_error(
        {"model_mesh": {"error": rec}}
    )
    rec |= {"statistic": 1.2}
    assert "little along it" in _mesh_error({"model_mesh": {"error": rec}})
    rec = {"status": "unavailable", "size_mm": 16.8, "reason": "no model on a 16.8 mm mesh: x"}
    assert _mesh_error({"model_mesh": {"error": rec}}).endswith("not absorbed: " + rec["reason"])


def _fake_problem(points, base, solve):
    """A Problem for the limits without FE: ``solve`` returns the stacked residual's
    blocks as 'positions', which ``residuals`` passes on unchanged."""
    return SimpleNamespace(
        scans=SCANS,
        points=points,
        base=base,
        solve=solve,
        residuals=lambda n, pos, dpos, nz: SimpleNamespace(r=pos),
        fm=SimpleNamespace(set_effects=lambda v: None),
    )


def _limit_problem(
    linear, effect: str, saturation: float, fails_above: float = np.inf, fails_below: float = 0.0
):
    """A null fit, its screen and a model whose effect's print saturates (no FE).

    The effect at distance ``s`` from neutral (one-step units) with ``ln c1 = theta0 -
    h(s) + x`` gives the residual ``r0 - g(s) P + x J - (x^2 / 2) Q``: ``g(s) = s / (1 +
    s / saturation)``, ``P`` the 'tilt' pattern and ``Q`` the 'bump' (both orthogonal to
    ``J``), ``h(s) = 0.3 s / d`` the c1-like part of the effect (``d`` the detectable
    size; a stiff skin passes for a stiffer c1: skin x8 for c1 x1.3). The planted bulk
    c1 that the null fit takes for its own (``theta0``) is at ``x = 0`` (its normal
    equation ``J' Delta = 0``), where the screen's estimate of the planted print is
    ``g(s)`` exactly (the influence vector is orthogonal to ``J`` and takes ``P``, the
    column, to 1). Planted at the null fit's own c1 (``x = h``) it would be ``g(s) +
    (h^2 / 2) a' Q``; ``Q`` is scaled so that is ``g(s) - 2 d`` at ``s = d``: negative,
    as the skin's was on the twins. A c1 left :data:`C1_TOL` off moves the estimate by
    at most ``(C1_TOL^2 / 2) |a' Q|``, 6e-4 d.
    """
    import fem
    from calib.discrepancy.screen import influence

    sample, J, _, sampler = linear

    def off_J(v):
        return v - J * float(J @ v) / float(J @ J)

    P, Q = off_J(misfit_pattern(sample, kind="tilt")), off_J(misfit_pattern(sample, kind="bump"))
    r0 = _at_fit(J, sampler.draw(np.random.default_rng(4))[:, 0])
    sign = -1.0 if effect == "poisson" else 1.0  # nu = nu0 - s: dr/dnu = +P
    fields = _fields(sample, r0, J, {effect: -sign * P, "p2": -misfit_pattern(sample)})
    rows = screen(fields, _points(sample)).screening.effects
    d = next(e.detectable for e in rows if e.name == effect)
    Q = Q * (-2.0 * d) / (0.3**2 / 2.0 * float(influence(fields, _points(sample), effect) @ Q))
    nu0 = 0.499
    base = EffectValues(nu=nu0)
    blocks = dict(zip(SCANS, sample.blocks, strict=True))

    def s_of(values) -> float:
        return nu0 - values.nu if effect == "poisson" else values.skin_ratio - 1.0

    def solve(theta, values, names, *, gradient, nuisance=None):
        s = s_of(values)
        if s > fails_above or s < fails_below:
            raise fem.ConvergenceError(f"no solution at s = {s}")
        g = s / (1.0 + s / saturation)
        x = theta - 6.0 + 0.3 * s / d
        r = r0 - g * P + x * J - x**2 / 2.0 * Q
        return {n: SimpleNamespace(positions_mm=r[blocks[n]]) for n in names}

    prob = _fake_problem(_points(sample), base, solve)
    null = SimpleNamespace(
        fields=fields,
        theta=6.0,
        nuisance={},
        effects=(),
        values=base,
        names=("theta",),
        x=np.array([6.0]),
        lower=np.array([5.0]),
        upper=np.array([7.0]),
        jacobian=lambda: J[:, None],
    )
    return prob, null, screen(fields, _points(sample))


@pytest.mark.parametrize("effect", ["skin", "poisson"])
def test_a_parameter_limit_is_where_the_planted_print_reaches_the_detectable_size(linear, effect):
    # Closed form: g(s) = d at s = d / (1 - d / saturation). With saturation 2 d the
    # limit is 2 d: twice the linearisation; the search's own tolerance (rtol 5 %) on g
    # is the test's. A linear print (no saturation) is found at the first step, s = d.
    from calib.discrepancy.limits import C1_TOL, parameter_limit

    prob, null, scr = _limit_problem(linear, effect, saturation=np.inf)
    d = next(e.detectable for e in scr.screening.effects if e.name == effect)
    lim = parameter_limit(prob, null, scr, effect, say=lambda m: None)
    assert lim.status == "reached" and len(lim.steps) == 1
    assert lim.distance == pytest.approx(d, rel=1e-12)
    assert lim.elasticity is None and not lim.saturated  # one size: no secant

    prob, null, scr = _limit_problem(linear, effect, saturation=2.0 * d)
    lim = parameter_limit(prob, null, scr, effect, say=lambda m: None)
    assert lim.status == "reached" and len(lim.steps) <= 8
    # the planted bulk c1 over the null fit's: exp(-h(s)) (one Gauss-Newton step: x
    # enters linearly along J), to the step tolerance
    for s_, _, ratio in lim.steps:
        assert np.log(ratio) == pytest.approx(-0.3 * s_ / d, abs=C1_TOL)
    g = lim.distance / (1.0 + lim.distance / (2.0 * d))
    assert g >= 0.95 * d and g == pytest.approx(d, rel=0.05)
    assert lim.linearised_ratio == pytest.approx(2.0, rel=0.25)
    # d ln g / d ln s = 1 / (1 + s / saturation): 1/2 at the limit; a secant through
    # sizes within a factor 4 of it lies between 1/5 and 4/5 (the ends' tangents)
    assert 0.2 < lim.elasticity < 0.8 and not lim.saturated
    expected = 0.499 - lim.distance if effect == "poisson" else 1.0 + lim.distance
    assert lim.value == pytest.approx(expected)
    # the sizes the search tried short of the limit (estimate under d, beyond the 5 %
    # tolerance) lie on the side opposite the visible one: inside the limit
    short = [0.499 - s_ if effect == "poisson" else 1.0 + s_ for s_, e_, _ in lim.steps]
    short = [v for v, (_, e_, _) in zip(short, lim.steps, strict=True) if e_ < 0.95 * d]
    side = lim.as_json()["visible"]
    assert side == ("below" if effect == "poisson" else "above") and short
    assert all((v > lim.value) if side == "below" else (v < lim.value) for v in short)


def test_a_print_that_saturates_below_the_detectable_size_is_beyond_the_range(linear):
    # sup g = saturation = d / 2 < d: even the range's end (excess ratio 99) falls short
    from calib.discrepancy.limits import SATURATED_BELOW, parameter_limit

    prob, null, scr = _limit_problem(linear, "skin", saturation=np.inf)
    d = next(e.detectable for e in scr.screening.effects if e.name == "skin")
    prob, null, scr = _limit_problem(linear, "skin", saturation=0.5 * d)
    lim = parameter_limit(prob, null, scr, "skin", say=lambda m: None)
    assert lim.status == "beyond the range" and lim.value is None
    assert lim.steps[-1][0] == pytest.approx(99.0) and lim.steps[-1][1] < d
    # g's elasticity 1 / (1 + s / saturation) is under 1e-3 beyond s = 50 (saturation
    # d / 2 = 0.034 here): saturated, and the summary says so
    assert lim.saturated and lim.elasticity < SATURATED_BELOW
    from calib.report.diagnosis import detection_limits

    entry = {"kind": "material", "significant": False, "detectable": d}
    doc = {"effects": {"skin": entry | {"parameter_limit": lim.as_json()}}}
    line = detection_limits(doc)
    assert "skin beyond its physical range (skin c1 / bulk c1; its print saturates" in line

    # the model has no solution past 1.5 d on the way to a limit of 2 d
    prob, null, scr = _limit_problem(linear, "skin", saturation=2.0 * d, fails_above=1.5 * d)
    lim = parameter_limit(prob, null, scr, "skin", say=lambda m: None)
    assert lim.status == "no FE solution" and lim.value is None

    # none at the first size (1.01 d and below; a stiff plate's recovery on springs): once,
    # 1.5 times it (a linear print: the estimate is 1.5 d), then bisection above the
    # failed size; the limit found is an upper bound, which the note says
    prob, null, scr = _limit_problem(linear, "skin", saturation=np.inf, fails_below=1.01 * d)
    lim = parameter_limit(prob, null, scr, "skin", say=lambda m: None)
    assert lim.status == "reached" and 1.01 * d < lim.distance <= 1.5 * d
    assert lim.steps[0][0] == pytest.approx(1.5 * d)
    assert "no FE solution" in lim.note and lim.upper_bound
    doc = {"effects": {"skin": entry | {"parameter_limit": lim.as_json()}}}
    assert "no solution nearer neutral, where the limit may lie" in detection_limits(doc)
    assert all(step[0] <= 1.5 * d for step in lim.steps)


def test_a_limit_at_a_refit_moves_the_named_effects_parameters_too(linear):
    # At a refit with skin named, nu's limit: the planted print g(s) P (saturation 2 d)
    # comes with a c1-like part (ln c1 down 0.3 s / d) and a skin-like part (the skin's
    # parameter down 0.3 s / d) that enters the residual through y N - (y^2 / 2) Q, y
    # the skin parameter's offset. P and Q are orthogonal to J and N (the skin's
    # column), so Gauss-Newton on both parameters finds y = 0 and the estimate is g(s)
    # exactly: the limit is where g = d (2 d, within the search's 5 %). On c1 alone y
    # would stay at 0.3 s / d and the estimate would be g(s) - 2 d (s / d)^2 < 0 (Q
    # scaled so): no limit.
    from calib.discrepancy.limits import C1_TOL, parameter_limit
    from calib.discrepancy.screen import influence

    sample, J, _, sampler = linear

    def off(v, *basis):
        B = np.column_stack(basis)
        return v - B @ np.linalg.lstsq(B, v, rcond=None)[0]

    N = off(misfit_pattern(sample), J)
    P = off(misfit_pattern(sample, kind="tilt"), J, N)
    Q = off(misfit_pattern(sample, kind="bump"), J, N)
    r0 = off(sampler.draw(np.random.default_rng(4))[:, 0], J, N)  # the refit's residual
    fields = _fields(sample, r0, J, {"skin": N, "poisson": P, "p2b": -misfit_pattern(sample)})
    pts = _points(sample)
    scr = screen(fields, pts, absorbed=("skin",))
    d = next(e.detectable for e in scr.screening.effects if e.name == "poisson")
    a = influence(fields, pts, "poisson", absorbed=("skin",))
    assert abs(float(a @ N)) < 1e-9 * np.linalg.norm(a) * np.linalg.norm(N)
    # the estimate of nu's print is -a' Delta (nu = nu0 - s): the Q term is -2 d at s = d
    Q = Q * (-2.0 * d) / (0.3**2 / 2.0 * -float(a @ Q))
    nu0, v_fit = 0.499, 3.0
    values = LIBRARY["skin"].set(EffectValues(nu=nu0), v_fit)
    blocks = dict(zip(SCANS, sample.blocks, strict=True))

    def solve(theta, vals, names, *, gradient, nuisance=None):
        s = nu0 - vals.nu
        x = theta - 6.0 + 0.3 * s / d
        y = vals.skin_ratio - 1.0 - v_fit + 0.3 * s / d
        g = s / (1.0 + s / (2.0 * d))
        r = r0 - g * P + x * J + y * N - y**2 / 2.0 * Q
        return {n: SimpleNamespace(positions_mm=r[blocks[n]]) for n in names}

    prob = _fake_problem(pts, EffectValues(nu=nu0), solve)
    fit = SimpleNamespace(
        fields=fields,
        theta=6.0,
        effects=("skin",),
        values=values,
        names=("theta", "skin"),
        x=np.array([6.0, v_fit]),
        lower=np.array([5.0, -0.9]),
        upper=np.array([7.0, 99.0]),
        jacobian=lambda: np.column_stack([J, N]),
    )
    say = lambda m: None  # noqa: E731
    lim = parameter_limit(prob, fit, scr, "poisson", absorbed=("skin",), say=say)
    assert lim.status == "reached" and lim.model == ("skin",)
    assert lim.as_json()["model"] == ["skin"]
    from calib.report.diagnosis import detection_limits

    entry = {"kind": "material", "significant": False, "detectable": d}
    doc = {"named": ["skin"], "effects": {"poisson": entry | {"parameter_limit": lim.as_json()}}}
    line = detection_limits(doc)
    assert f"(full FE, at the model with skin): poisson {lim.value:.3g} or less (nu)" in line
    assert "(one-step at the null fit, linearised at neutral): poisson" in line
    g = lim.distance / (1.0 + lim.distance / (2.0 * d))
    assert g >= 0.95 * d and g == pytest.approx(d, rel=0.05)
    assert lim.value == pytest.approx(nu0 - lim.distance)
    for s_, _, ratio in lim.steps:  # the c1 part, to the Gauss-Newton tolerance
        assert np.log(ratio) == pytest.approx(-0.3 * s_ / d, abs=C1_TOL)
    with pytest.raises(ValueError, match="in the fit already"):
        parameter_limit(prob, fit, scr, "skin", absorbed=("skin",), say=say)
    # with c1 alone in the steps (the named skin held at its fit) there is no limit
    held = SimpleNamespace(**(vars(fit) | {"names": ("theta",), "x": np.array([6.0])}))
    held.lower, held.upper, held.jacobian = fit.lower[:1], fit.upper[:1], lambda: J[:, None]
    assert parameter_limit(prob, held, scr, "poisson", absorbed=("skin",), say=say).status in (
        "not settled",
        "beyond the range",
    )


def test_the_limits_figure_shows_each_search_and_the_model_it_ran_at():
    from calib.report.diagnosis import limits_figure

    steps = [[1.0, 0.8, 0.97], [1.25, 0.99, 0.96]]
    reached = {"status": "reached", "value": 2.25, "quantity": "skin c1 / bulk c1"}
    reached |= {"distance": 1.25, "detectable": 1.0, "steps": steps, "model": ["poisson"]}
    beyond = {"status": "beyond the range", "value": None, "quantity": "inclusion c1 / bulk c1"}
    beyond |= {"distance": None, "detectable": 2.5, "steps": [[2.5, 1.2, 1.0], [99.0, 2.3, 1.0]]}
    effects = {
        "skin": {"parameter_limit": reached},
        "inclusions": {"parameter_limit": beyond},
        "sliding": {"parameter_limit": {"status": "no FE solution", "steps": []}},
        "density": {"parameter_limit": None},
    }
    fig = limits_figure(effects)
    assert [ax.get_title() for ax in fig.axes] == [
        "skin: 2.25 (skin c1 / bulk c1)",
        "inclusions: beyond the range",
    ]
    assert fig.get_suptitle() == "parameter limits at the model with poisson (full FE)"
    x, y = fig.axes[1].lines[1].get_data()  # the search's sizes and estimates, in order
    assert list(x) == [2.5, 99.0] and list(y) == [1.2, 2.3]
    assert limits_figure({"sliding": effects["sliding"], "density": {}}) is None


def _bench_module():
    """``benchmarks/bench_diagnose.py`` as a module (the benchmarks are not a package)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[2] / "benchmarks" / "bench_diagnose.py"
    spec = importlib.util.spec_from_file_location("bench_diagnose", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def test_the_bench_says_whether_a_missed_truth_lies_inside_its_limit():
    # benchmarks/bench_diagnose.py's --table line: inside = nearer neutral than the limit
    # (springs stiffer, nu higher, a ratio lower); none without a reached limit
    bench = _bench_module()
    truth = dict(sliding_stiffness_pa_per_mm=1000.0, nu=0.45, inclusion_ratio=5.0)
    truth |= dict(skin_ratio=8.0, c2_pa=210.0)

    def row(hidden, value, status="reached"):
        screen = {"parameter_limit": {"status": status, "value": value}}
        return dict(hidden=hidden, truth_effects=truth, c1_true_pa=420.0, hidden_screen=screen)

    assert bench._inside_limit(row("sliding", 914.0)) is True
    assert bench._inside_limit(row("sliding", 1100.0)) is False
    assert bench._inside_limit(row("poisson", 0.455)) is False
    assert bench._inside_limit(row("inclusions", 33.7)) is True
    assert bench._inside_limit(row("skin", 2.7)) is False
    assert bench._inside_limit(row("mooney", 0.6)) is True  # c2 / c1 = 0.5
    assert bench._inside_limit(row("inclusions", None, "no FE solution")) is None
    assert bench._inside_limit({"hidden": "skin", "truth_effects": truth}) is None
    # the limit's own "visible" (diagnosis.json) is what decides; without it (older
    # files) calib.discrepancy.limits.visible_side
    flipped = row("sliding", 914.0)
    flipped["hidden_screen"]["parameter_limit"]["visible"] = "above"
    assert bench._inside_limit(flipped) is False


def test_the_bench_keeps_other_amplitudes_out_of_the_bars():
    # benchmarks/bench_diagnose.py: --sliding-springs and --inclusion-ratio name their
    # cases by amplitude; the bars count the preset amplitude only, the curve is the skin's
    import argparse

    bench = _bench_module()
    args = argparse.Namespace(
        cases="sliding,inclusions,none,curve",
        seeds="1",
        null_seeds="0",
        ratios="4",
        only=None,
        sliding_springs=300.0,
        inclusion_ratio=30.0,
    )
    cases = {name: specs for name, specs, _, _ in bench._cases(args)}
    assert cases == {
        "inclusions-r30-s1": ["inclusions=30"],
        "sliding-k300-s1": ["sliding=300"],
        "none-s0": ["none"],
        "skin-r4-s0": ["skin=1.5:4"],
    }
    preset = {n for n in cases if bench._at_preset({"case": n})}
    curve = {n for n in cases if bench._is_curve({"case": n})}
    assert preset == {"none-s0"} and curve == {"skin-r4-s0"}
    args.sliding_springs, args.inclusion_ratio = bench.SLIDING_SPRINGS_PA_PER_MM, None
    assert all(bench._at_preset({"case": n}) for n, *_ in bench._cases(args) if "-r4" not in n)


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--seeds", "0,x"], "--seeds takes a comma list of ints"),
        (["--cases", "skin,skn"], "--cases: unknown skn"),
        (["--mesh-series", "14,1e"], "--mesh-series takes a comma list of floats"),
        (["--rim-margin", "wide"], "--rim-margin must be a width in mm or 'element'"),
        (["--table"], "cases does not exist: run the matrix into --out first"),
        (["--mesh-series", "14", "--only", "none-s0"], "does not exist (--mesh-series --only"),
    ],
)
def test_the_bench_refuses_bad_arguments_before_it_writes(
    tmp_path, monkeypatch, capsys, argv, said
):
    # benchmarks/bench_diagnose.py: a bad argument is argparse's error (exit 2) naming it,
    # and OUT is left as it was (it created OUT/cases before checking, last note)
    bench = _bench_module()
    out = tmp_path / "out"
    monkeypatch.setattr("sys.argv", ["bench_diagnose.py", "--out", str(out), *argv])
    with pytest.raises(SystemExit) as exc:
        bench.main()
    assert exc.value.code == 2
    assert said in capsys.readouterr().err
    assert not out.exists()


def test_the_bench_prints_the_refits_in_physical_units():
    # --table's per-set block: the candidates of diagnosis.json (Candidate.as_json) with
    # the parameter as the README gives it (sliding's ln k as springs, a ratio - 1 as the
    # ratio), the explained share, and named or the reason it is not
    import math

    from calib.discrepancy.diagnose import Candidate

    bench = _bench_module()

    def cand(effect, params, explained, passes, reason=""):
        return Candidate(
            effect=effect,
            round=1,
            significant=True,
            p_holm=0.01,
            statistic=3.0,
            lopo_before_mm2=1.0,
            lopo_after_mm2=0.5,
            lopo_improves=True,
            parameters=params,
            at_bound=(),
            plausible=True,
            explained=explained,
            passes=passes,
            c1_pa=410.0,
            rms_mm=0.5,
            reason=reason,
            explained_all_points=explained,
        ).as_json()

    screen = {"statistic": 2.82, "standard_error": 0.75, "p_holm": 0.027}
    rows = [
        {
            "case": "sliding-k300-s0",
            "hidden": "sliding",
            "hidden_screen": screen,
            "named": ["sliding"],
            "confounded_with": [],
            "candidates": [
                cand("sliding", {"sliding": math.log(311.0)}, 0.92, True),
                cand(
                    "inclusions",
                    {"inclusions": 10.8},
                    0.32,
                    False,
                    "explains 32 % < 50 % of the residual above the noise floor",
                ),
            ],
        },
        {
            "case": "none-s0",
            "hidden": "none",
            "hidden_screen": None,
            "named": [],
            "confounded_with": [],
            "candidates": [cand("skin", {"skin": 1.0}, 0.1, False, "x")],
        },
        {
            "case": "skin-r4-s0",
            "hidden": "skin",
            "hidden_screen": screen,
            "named": [],
            "confounded_with": [],
            "candidates": [],
        },
    ]
    lines = bench._detail_lines(rows)
    assert lines == [
        "sliding-k300-s0: sliding screen t 2.82, se 0.75, Holm p 0.027; refits: sliding "
        "springs 311 Pa/mm, explains 92 % (named); inclusions ratio 11.8, explains 32 % "
        "(explains 32 % < 50 % of the residual above the noise floor)"
    ]


def test_an_interval_cut_to_the_admissible_values_keeps_its_coverage():
    # The truth lies in ADMISSIBLE, so "truth in the cut interval" is the same event as
    # "truth in the interval": checked draw by draw on seeded Wald intervals about
    # truths at and near the range's ends (the coverage is then equal, not close).
    from calib.discrepancy.diagnose import _admissible_interval
    from calib.model.effects import ADMISSIBLE

    # inclusions seed 2 at ratio 30 (bench_diagnose --inclusion-ratio 30): ratio - 1
    # 28.3 with a Wald interval reaching a negative stiffness
    assert _admissible_interval("inclusions", -133.1, 189.8) == (-1.0, 189.8)
    assert _admissible_interval("poisson", 0.45, 0.52) == (0.45, 0.5)
    assert _admissible_interval("theta", -9.0, 9.0) == (-9.0, 9.0)  # no admissible range
    assert _admissible_interval("mooney", -0.5, -0.1) == (0.0, 0.0)  # entirely outside
    rng = np.random.default_rng(13)
    for name, truths in {"inclusions": (-0.99, -0.5), "poisson": (0.49, 0.499)}.items():
        a, b = ADMISSIBLE[name]
        for truth in truths:
            se = 0.6 if name == "inclusions" else 0.01
            est = truth + se * rng.standard_normal(4000)
            lo, hi = est - 1.96 * se, est + 1.96 * se
            cut = np.array([_admissible_interval(name, x, y) for x, y in zip(lo, hi, strict=True)])
            assert np.all(cut[:, 0] >= a) and np.all(cut[:, 1] <= b)
            inside = (lo <= truth) & (truth <= hi)
            assert np.array_equal(inside, (cut[:, 0] <= truth) & (truth <= cut[:, 1]))
            assert np.any(cut != np.column_stack([lo, hi]))  # some were cut


def test_the_refit_parameters_read_as_the_quantities_the_library_names():
    # skin and inclusions are refitted as ratio - 1 (admissible above -1: a positive
    # ratio), sliding as ln k within sliding_ln_k_bounds (10 to 1e6 Pa/mm for the twins'
    # 1000 Pa/mm probe, refit.py); exact up to the exponential's round-off
    from calib.model.effects import ADMISSIBLE

    for name in ("skin", "inclusions"):
        assert PHYSICAL[name].convert(ADMISSIBLE[name][0]) == 0.0
        assert PHYSICAL[name].convert(7.0) == 8.0
    springs = [PHYSICAL["sliding"].convert(b) for b in sliding_ln_k_bounds(1000.0)]
    assert springs == pytest.approx([10.0, 1e6], rel=1e-12)
    assert set(PHYSICAL) <= set(LIBRARY)


def test_the_model_error_parts_pool_to_the_share_s_mean_square():
    # bench_diagnose --model-error's rows by scan, localisation region and height band:
    # each part's centred mean square, weighted by its points, pools back to the mean
    # square the share is judged on (calib.discrepancy.diagnose._centred_ms), a second
    # code path; the parts' shares of what the effect adds read the same formula
    from calib.discrepancy.diagnose import _centred_ms

    bench = _bench_module()
    rng = np.random.default_rng(3)
    res = {"a": rng.normal(0.2, 0.1, 50), "b": rng.normal(-0.1, 0.3, 80)}
    judged = {n: rng.random(len(r)) < 0.7 for n, r in res.items()}
    kinds = {
        "region": {n: rng.choice(["apex", "bulk", "rim"], int(k.sum())) for n, k in judged.items()},
        "height": {n: rng.choice(["14-20 mm", ">45 mm"], int(k.sum())) for n, k in judged.items()},
    }
    parts = bench._ms_by_part(res, judged, kinds)
    total = _centred_ms(SimpleNamespace(residual=res), judged)
    for kind in ("scan", "region", "height"):
        mine = [v for k, v in parts.items() if k.startswith(kind + " ")]
        n = sum(k for _, k in mine)
        assert n == sum(int(k.sum()) for k in judged.values())
        assert sum(ms * k for ms, k in mine) / n == pytest.approx(total, rel=1e-12)
    after = {k: (0.5 * ms, n) for k, (ms, n) in parts.items()}
    null = {k: (0.25 * ms, n) for k, (ms, n) in parts.items()}
    rows = bench._parts(parts, after, null)  # half of each part removed, a quarter left
    assert all(r["of_added"] == pytest.approx(2 / 3) for r in rows.values())


def test_the_holdout_never_leaves_a_single_scan_to_fit(caplog):
    # one calibration and one validation scan: holding out the validation scan left one
    # scan, leave-one-posture-out could not run and every candidate failed (`unexplained`)
    from calib.discrepancy.problem import choose_scans

    def work(**roles):
        return SimpleNamespace(
            path="W", record={"scans": {n: {"role": r} for n, r in roles.items()}}
        )

    with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
        assert choose_scans(work(lat="calibration", tilt="validation"), None) == (
            ["lat", "tilt"],
            None,
        )
    assert "holding out tilt would leave 1 scan(s) to fit" in caplog.text
    with pytest.raises(
        DiagnosisError, match=r"^holdout \(--holdout\) tilt: leaves \['lat'\] to fit"
    ):
        choose_scans(work(lat="calibration", tilt="validation"), "tilt")
    three = work(a="calibration", b="calibration", v="validation")
    assert choose_scans(three, None) == (["a", "b"], "v")
    assert choose_scans(three, "a") == (["b", "v"], "a")
    caplog.clear()
    with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
        assert choose_scans(work(a="calibration"), None) == (["a"], None)
    assert "a single scan to fit (a): leave-one-posture-out cannot run" in caplog.text
    # review W: a scan whose calibrated state failed was left out without a word
    four = work(a="calibration", b="calibration", c="calibration", v="validation")
    four.record["scans"]["b"]["failed"] = "Newton did not converge at 2 g"
    caplog.clear()
    with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
        assert choose_scans(four, None) == (["a", "c"], "v")
    assert "no FE solution at the calibrated c1: b (Newton did not converge" in caplog.text


def test_a_diagnosis_model_said_to_differ_is_not_the_calibrations_own():
    # a --reference-state prestress calibration diagnosed with a straight recovery on its own
    # mesh had the same node count: the gap's "before" was the prestressed calibration's
    # states against an "after" of the straight model, the reference state's change
    # credited to the named effect
    from calib.discrepancy.problem import Problem

    mesh = SimpleNamespace(n_nodes=100)

    def same(diagnosis_mesh, note):
        prob = SimpleNamespace(mesh=diagnosis_mesh, work=SimpleNamespace(mesh=mesh), mesh_note=note)
        prob.own_mesh = Problem.own_mesh.fget(prob)
        return prob.own_mesh, Problem.same_mesh.fget(prob)

    assert same(mesh, "") == (True, True)
    assert same(mesh, "prestressed") == (True, False)  # its own mesh, another reference
    assert same(SimpleNamespace(n_nodes=90), "") == (False, False)


def test_a_diagnosis_refit_is_not_diagnosed_as_a_calibration():
    # its model.effects were ignored: the problem was built as c1 alone while its saved
    # states (the gap's "before") include the effects
    from calib.discrepancy.problem import build_problem

    record = {
        "model": {"effects": {"named": ["skin"]}},
        "diagnosis": {"named": ["skin"], "source_work": "WORK"},
        "scans": {},
    }
    with pytest.raises(DiagnosisError, match=r"a diagnosis \(named: skin\); diagnose .* \(WORK\)"):
        build_problem(SimpleNamespace(path="WORK/diagnosis/refit", record=record))


def test_a_held_out_scan_without_a_solution_keeps_its_before_and_says_why(monkeypatch):
    # the held-out posture is solved only at the end, with the final model: its failure
    # ended the whole run with the bare fem message and no diagnosis.json
    import importlib

    import calib.model.residuals as residuals
    import fem

    dg = importlib.import_module("calib.discrepancy.diagnose")

    def metrics(scan, positions_mm, faces, nipple, tumour):
        mean = float(positions_mm.mean())
        return SimpleNamespace(surface_error_mm={"fiducial": {"mean": mean}},
                               nipple_error_mm={"fiducial": mean})  # fmt: skip

    monkeypatch.setattr(dg, "scan_metrics", metrics)
    monkeypatch.setattr(residuals.SimulatedSurface, "of", staticmethod(lambda mesh: mesh))
    null, final = _fit(430.0), _fit(415.0)
    # (diagnosis mesh, failing c1s, final model, the held-out scan's before): on another
    # mesh c1 alone is solved there; where it fails too (nothing named: the final model
    # is c1 alone), the calibration's own
    cases = [
        (False, (415.0,), final, 430.0),
        (True, (415.0,), final, 0.0),
        (False, (430.0,), null, 0.0),
        (False, (415.0, 430.0), final, 0.0),
    ]
    for same_mesh, failing, final, before in cases:
        prob, solved = _gap_problem(same_mesh=same_mesh)
        plain = prob.solve

        def solve(theta, values, names, gradient, nuisance, plain=plain, failing=failing):
            if "h" in names and np.isclose(np.exp(theta), failing).any():
                raise fem.ConvergenceError("load factor 0.6")
            return plain(theta, values, names, gradient, nuisance)

        prob.solve = solve
        say = []
        gaps, states = dg._gaps(prob, null, final, say.append)
        assert set(states) == {"a", "b"} and set(gaps) == {"a", "b", "h"}
        doc = gaps["h"].as_json(floor_mm=0.0)
        assert doc["failed"] == "no FE solution with the final model (load factor 0.6)"
        assert "after" not in doc["surface_error_mm"] and "cut_above_floor" not in doc
        assert doc["surface_error_mm"]["before"]["mean"] == pytest.approx(before)
        after = float(np.exp(final.theta))
        assert gaps["a"].as_json(0.0)["surface_error_mm"]["after"]["mean"] == pytest.approx(after)
        assert any("h (held out): no FE solution" in s for s in say)


def test_effects_that_cannot_be_tested_are_said():
    # `--effects inclusions` on a phantom without inclusions answered `no missing effect`
    # from the misfit test alone, without a word
    from calib.discrepancy.diagnose import _none_testable

    why = {"inclusions": "no inclusion was detected in the reference scan"}
    said = _none_testable(("inclusions",), why)
    assert said.startswith("none of the effects asked for can be tested (inclusions: no inc")
    assert "misfit test alone" in said
    assert _none_testable(("inclusions", "skin"), why) is None  # skin is tested


def test_the_calibration_s_mesh_bound_is_carried_to_the_diagnosis_mesh_size():
    # review W: the calibration's GCI of ln c1 was added unchanged to the refit's c1
    # interval on any diagnosis mesh; it describes the calibration's mesh. Then none was
    # added on another mesh, and a diagnosis moved to the next size reported a noise-only
    # interval that missed the truth (review AO's set: 411.9-415.1 Pa at 420). Now the
    # bound is carried to the diagnosis mesh's size by the check's order.
    from calib.discrepancy.diagnose import _intervals

    sample = phantom_sample(300, 2, seed=2)
    J = sag_sensitivity(sample)
    r = np.random.default_rng(0).normal(0.0, 0.1, sample.n)
    fit = SimpleNamespace(
        fields=_fields(sample, r, J, {}),
        jacobian=lambda: J[:, None],
        x=np.array([np.log(420.0)]),
        names=("theta",),
    )
    check = {
        "gci_ln_c1": 0.05,
        "mesh_size_mm": 12.0,
        "order": 1.6,
        "convergence": "assumed order",
        "meshes": [{"mesh_size_mm": 16.8}],
    }
    record = {"uncertainty": {"mesh_check": check}}
    work = SimpleNamespace(record=record, mesh=SimpleNamespace(n_nodes=100))

    def theta_at(nodes, size_mm, mesh_check=check):
        work.record["uncertainty"]["mesh_check"] = mesh_check
        prob = SimpleNamespace(points=_points(sample), work=work, imaged_unlike=False,
                               mesh=SimpleNamespace(n_nodes=nodes), region_scale=1.0,
                               own_mesh=nodes == 100, mesh_size_mm=size_mm)  # fmt: skip
        theta = _intervals(fit, prob)["theta"]
        lo, hi = theta["c1_ci95_pa"]
        return theta, np.log(hi / lo)

    own, w_own = theta_at(100, 12.0)
    assert own["gci_ln_c1"] == 0.05 and own["gci_from"].endswith("on this mesh")
    coarser, w_coarser = theta_at(140, 14.0)
    assert coarser["gci_ln_c1"] == pytest.approx(0.05 * (14 / 12) ** 1.6, rel=1e-12)
    assert "carried to this 14 mm" in coarser["gci_from"]
    assert "extrapolated" not in coarser["gci_from"]  # inside the sizes checked, 12-16.8
    assert theta_at(150, 12.0)[0]["gci_from"].endswith("on this other mesh of that size")
    far = theta_at(170, 20.0)[0]["gci_from"]
    assert "(extrapolated beyond the sizes checked, 12-16.8 mm)" in far
    work.record["reference_recovery"] = {"method": "spatial"}  # review AR
    assert theta_at(140, 14.0)[0]["gci_from"].endswith("where this mesh has straight ones")
    del work.record["reference_recovery"]
    finer, w_finer = theta_at(160, 10.0)
    assert finer["gci_ln_c1"] == pytest.approx(0.05 * (10 / 12) ** 1.6, rel=1e-12)
    assert w_finer < w_own < w_coarser
    # the summary says what widened the interval (review AR: the README's figures were in
    # diagnosis.json only); an older record without `gci_from` still reads
    from calib.report.diagnosis import _mesh_bound_line

    line = _mesh_bound_line(coarser)
    assert f"{100 * coarser['gci_ln_c1']:.2g} % of c1 (the calibration's mesh check on" in line
    lo, hi = coarser["noise_only_c1_ci95_pa"]
    assert line.endswith(f"the noise alone {lo:.1f} - {hi:.1f} Pa")
    old = {k: v for k, v in coarser.items() if k != "gci_from"}
    assert "(the calibration's mesh check);" in _mesh_bound_line(old)
    for bad, why in (({}, "ran no mesh check"), ({"gci_ln_c1": None}, "check failed"),
                     ({"gci_ln_c1": 0.05}, "does not give its mesh size")):  # fmt: skip
        theta, _ = theta_at(140, 14.0, bad)
        assert theta["gci_ln_c1"] is None and why in theta["gci_from"]
        assert theta["c1_ci95_pa"] == theta["noise_only_c1_ci95_pa"]  # the noise's alone
        assert _mesh_bound_line(theta) is None


def test_the_report_s_rim_band_is_the_one_the_maps_use():
    # review W: the report said 10 mm where the maps' band is 10 mm times region_scale
    from calib.report.diagnosis import _rim

    assert "within 10 mm" in _rim({"scans": {"rim_margin_mm": 5.0}})  # before region_scale
    assert "within 7 mm" in _rim({"scans": {"rim_margin_mm": 5.0, "region_scale": 0.7}})
    assert "within 12 mm" in _rim({"scans": {"rim_margin_mm": 12.0, "region_scale": 0.7}})


def test_scans_imaged_unlike_are_told_from_their_imaging_not_their_residual(tmp_path):
    # review W: one noise level for every scan made a noisier scan's columns screen
    # significant on noise. The residual's own short-lag spread cannot say so (on the
    # quick skin twin, imaged alike, it was 0.33 mm on the right lateral scan and 0.20
    # on the 50 degree one: element-scale misfit), so the imaging says: voxel size x
    # image noise (the quick twins: 1.06 at most between scans, under 1.5)
    import json

    from calib.discrepancy.problem import IMAGED_UNLIKE_RATIO, Problem, imaging_noise_mm

    def scan(name, voxel, noise):
        (tmp_path / "scans" / name).mkdir(parents=True)
        doc = {"voxel_size_mm": voxel, "quality": {"seg_noise_sigma_rel": noise}}
        (tmp_path / "scans" / name / "ingest.json").write_text(json.dumps(doc))

    scan("lat", [1.5, 1.5, 1.5], 0.044)  # a quick twin's right lateral scan before
    scan("tilt", [1.5, 1.5, 1.5], 0.039)  # ingest revision 6, its 50 degree one (1.13)
    scan("thick", [1.5, 1.5, 5.0], 0.044)  # 5 mm slices: 3.14 mm rms edge
    scan("old", [1.5, 1.5, 1.5], None)  # an ingest without the figure
    work = SimpleNamespace(path=tmp_path)
    noise = {n: imaging_noise_mm(work, n) for n in ("lat", "tilt", "thick", "old")}
    assert noise["lat"] == pytest.approx(1.5 * 0.044) and noise["old"] is None
    assert noise["thick"] == pytest.approx(np.sqrt((2 * 1.5**2 + 5.0**2) / 3) * 0.044)
    for scans, unlike in ((["lat", "tilt"], False), (["lat", "thick"], True),
                          (["lat", "old"], False)):  # fmt: skip
        known = {n: noise[n] for n in scans if noise[n] is not None}
        prob = SimpleNamespace(scans=scans, imaging_noise_mm=known)
        assert Problem.imaged_unlike.fget(prob) is unlike
    assert 1.13 < IMAGED_UNLIKE_RATIO < noise["thick"] / noise["lat"]


def test_scans_whose_noise_was_measured_in_different_ways_are_not_compared(tmp_path, caplog):
    # review AF: the background's and the interior's estimates disagree on correlated
    # noise (0.47-0.86 of the truth on an interpolated image): two scans of equal noise
    # measured the two ways could be called imaged unlike
    import json

    from calib.discrepancy.problem import comparable_imaging_noise

    def scan(name, noise, method):
        (tmp_path / "scans" / name).mkdir(parents=True)
        quality = {"seg_noise_sigma_rel": noise} | ({"seg_noise_method": method} if method else {})
        doc = {"voxel_size_mm": [1.5, 1.5, 1.5], "quality": quality}
        (tmp_path / "scans" / name / "ingest.json").write_text(json.dumps(doc))

    scan("a", 0.033, None)  # before ingest revision 7: the background's
    scan("b", 0.030, "background (offset)")  # one way with "background"
    scan("c", 0.018, "interior")
    work = SimpleNamespace(path=tmp_path)
    assert comparable_imaging_noise(work, ["a", "b"]) == pytest.approx(
        {"a": 1.5 * 0.033, "b": 1.5 * 0.030}
    )
    with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
        alike = comparable_imaging_noise(work, ["a", "c"])
    assert "measured in different ways (a background, c interior" in caplog.text
    # review AH: only the voxels compared, not dropped (a 4 mm scan's ratio kept): here
    # equal voxels, so equal figures at the median image noise
    assert alike == pytest.approx({"a": 1.5 * 0.0255, "c": 1.5 * 0.0255})


def test_inclusions_too_large_for_ingest_are_said_to_be_left_out(tmp_path, caplog):
    # review W: the inclusions effect tags what ingest found; a region of inclusion
    # contrast larger than ingest accepts was left out of it without a word in diagnose
    import json

    from calib.discrepancy.problem import inclusions_left_out, reference_inclusions

    (tmp_path / "scans" / "ref").mkdir(parents=True)
    inclusion = {"centre_lps_mm": [1.0, 2.0, 3.0], "diameter_mm": 8.0}
    doc = {"inclusions": [inclusion], "quality": {"inclusions_too_large": 1}}
    (tmp_path / "scans" / "ref" / "ingest.json").write_text(json.dumps(doc))
    ref = SimpleNamespace(name="ref", T_ref_from_scan=np.eye(4))
    work = SimpleNamespace(path=tmp_path, measurements=SimpleNamespace(reference=ref))
    with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
        (inc,) = reference_inclusions(work)
    assert inc[1] == 8.0 and inclusions_left_out(work) == 1
    assert "left out 1 region(s) of inclusion contrast too large" in caplog.text
    assert "tags only the 1 it found" in caplog.text
    del doc["quality"]  # an older ingest: not counted
    (tmp_path / "scans" / "ref" / "ingest.json").write_text(json.dumps(doc))
    assert inclusions_left_out(work) == 0


def test_the_noise_model_s_range_follows_the_body_s_size():
    # review W: the variograms reached 40 mm (tests) and 20 mm (floor) on any body; on one
    # half the twins' height the noise model took part of a misfit for noise (its length
    # 5.4 mm for a truth of 3; 3.0 with 20 mm lags). They scale like the regions: 1 for
    # every twin (72-78 mm)
    from calib.discrepancy.diagnose import FLOOR_LAG_MM, NOISE_LAG_MM
    from calib.discrepancy.problem import Problem

    def scale(height):
        return Problem.region_scale.fget(SimpleNamespace(body_height_mm=height))

    for height, k in ((75.0, 1.0), (72.0, 1.0), (78.0, 1.0), (37.5, 0.5), (150.0, 2.0)):
        assert scale(height) == k
    assert scale(0.0) == 1.0  # not measured
    assert (NOISE_LAG_MM, FLOOR_LAG_MM) == (40.0, 20.0)


def test_a_diagnosis_mesh_few_elements_tall_is_said(caplog):
    # review W: a fallback or asked size of the diagnosis' model mesh that leaves the body
    # fewer than 4 elements tall was not said (calibrate says so of its own)
    from calib.discrepancy.problem import _say_coarse

    with caplog.at_level("WARNING", logger="calib.discrepancy.problem"):
        assert not _say_coarse("W", 14.0, 75.0)  # the quick twins: 5.4 elements
        assert _say_coarse("W", 16.0, 40.0)  # a small body on a fallback size: 2.5
    assert "leaves the 40 mm tall body 2.5 elements tall, fewer than 4" in caplog.text
    assert "--mesh-size 7" in caplog.text


def test_scans_imaged_unlike_reach_the_floor_intervals_and_screen_at_their_levels(monkeypatch):
    # review X: the per-scan levels and the scaled lags were tested in calib.stats only.
    # Two scans, 0.1 and 0.3 mm of white noise, imaged unlike, a body half the twins'
    # height: the floor is the points' mean of the two levels (not the quiet scan's), the
    # variograms reach 20 and 10 mm, and the screen asks for the same; the intervals keep
    # one level (the series estimator takes each scan's scale from its residual)
    import importlib

    from calib.discrepancy.diagnose import _intervals, _noise_var

    diagnose_mod = importlib.import_module("calib.discrepancy.diagnose")  # not the function
    screen_mod = importlib.import_module("calib.discrepancy.screen")

    sample = phantom_sample(400, 2, seed=3)
    J = sag_sensitivity(sample)
    rng = np.random.default_rng(0)
    r = rng.normal(0.0, 1.0, sample.n) * np.where(sample.scan == 0, 0.1, 0.3)
    fields = _fields(sample, r, J, {})
    work = SimpleNamespace(record={}, mesh=SimpleNamespace(n_nodes=1))
    lags = []
    real = diagnose_mod.session_noise

    calls = []

    def spy(*args, **kw):
        lags.append(kw.get("max_lag_mm"))
        calls.append(SimpleNamespace(kwargs=kw))
        return real(*args, **kw)

    monkeypatch.setattr(diagnose_mod, "session_noise", spy)
    floor, se = {}, {}
    fit = SimpleNamespace(fields=fields, jacobian=lambda: J[:, None], x=np.zeros(1))
    fit.names = ("theta",)
    for unlike in (False, True):
        prob = SimpleNamespace(points=_points(sample), imaged_unlike=unlike, work=work)
        prob.region_scale, prob.mesh, prob.own_mesh = 0.5, SimpleNamespace(n_nodes=1), True
        floor[unlike] = _noise_var(fields, prob)
        se[unlike] = _intervals(fit, prob)["theta"]["standard_error"]
    assert lags == [10.0, 20.0, 10.0, 20.0]  # FLOOR_LAG_MM and NOISE_LAG_MM, times 0.5
    assert [c.kwargs.get("by_scan", False) for c in calls] == [False, False, True, False]
    # one level: the quiet scan's variance; each scan at its own: their mean (0.05). A
    # variance from 400 points has a relative sd of sqrt(2 / 400) = 7 %, more from the
    # variogram's short-lag bins that set the level: 30 % is 4 of those, and keeps the two
    # answers (a factor 5 apart) well apart
    assert floor[False] == pytest.approx(0.01, rel=0.3)
    assert floor[True] == pytest.approx(0.5 * (0.01 + 0.09), rel=0.3)
    # the intervals: of the refit's unweighted estimate, the sandwich's standard error
    # (white noise here; the refit fits no per-scan offset, so J whole: review AV, the
    # interval had J less each scan's mean, another estimator's, 2.1 times this one's on
    # this sag field), imaged alike or not; the series estimator takes the scale from 800
    # residuals (a standard error's relative sd about sqrt(1 / 800) = 3.5 %): 10 % is 3
    sigma = np.where(sample.scan == 0, 0.1, 0.3)
    sandwich = np.sqrt(np.sum(J**2 * sigma**2)) / np.sum(J**2)
    assert se[False] == se[True] == pytest.approx(sandwich, rel=0.1)
    seen = {}
    real_screen_noise = screen_mod.session_noise

    def screen_spy(*args, **kw):
        seen.update(kw)
        return real_screen_noise(*args, **kw)

    monkeypatch.setattr(screen_mod, "session_noise", screen_spy)
    screen_mod.screen(fields, _points(sample), by_scan=True, max_lag_mm=20.0)
    assert (seen["by_scan"], seen["max_lag_mm"]) == (True, 20.0)
    reused = screen_mod.screen(fields, _points(sample)).noise
    with pytest.raises(ValueError, match="by_scan=False, asked True"):
        screen_mod.screen(fields, _points(sample), noise=reused, by_scan=True)


def test_the_summary_says_what_the_diagnosis_left_out_or_weighted_apart():
    # review X: excluded scans, scans imaged unlike and inclusions left out were in the
    # log and diagnosis.json only
    from calib.report.diagnosis import _caveats

    doc = {"scans": {}, "noise": {}, "model_mesh": {}}  # an older diagnosis: nothing said
    assert _caveats(doc) == []
    doc = {
        "scans": {"excluded": {"flip": "Newton failed"}, "imaging_noise_mm": {"a": 0.066}},
        "noise": {"by_scan": True},
        "model_mesh": {"inclusions_left_out": 1},
    }
    said = "\n".join(_caveats(doc))
    assert "no FE solution at the calibrated c1: flip (Newton failed)" in said
    assert "scans imaged unlike (voxel x image noise a 0.066)" in said
    assert "leaves out 1 region(s) of inclusion contrast" in said


def test_a_refit_is_not_written_from_another_model_s_geometry(tmp_path):
    # write_refit writes the forward model's last stress-free mesh as the refit's: it
    # refuses where that is not the final model's (review AU: the null fit's, on another
    # mesh) or where it is a curved one (a refit records straight elements and no
    # prestress files), before anything is written
    from calib.workflows.diagnose import write_refit

    values = SimpleNamespace(name="neutral")
    work = SimpleNamespace(path=tmp_path, measurements=SimpleNamespace(
        reference=SimpleNamespace(name="ref")))  # fmt: skip

    def refit(**fm):
        fm = {"reference_state": "unload", "effects": values, "stress_free_theta": 6.0,
              "prestressed": False} | fm  # fmt: skip
        d = SimpleNamespace(
            problem=SimpleNamespace(work=work, fm=SimpleNamespace(**fm)), gaps={},
            final=SimpleNamespace(values=values, theta=6.0),
        )  # fmt: skip
        write_refit(tmp_path / "refit", d, {})

    with pytest.raises(RuntimeError, match="last recovery is not the final model's"):
        refit(stress_free_theta=5.9)
    with pytest.raises(RuntimeError, match="last recovery is not the final model's"):
        refit(effects=SimpleNamespace(name="skin"))
    with pytest.raises(RuntimeError, match="curved stress-free elements"):
        refit(prestressed=True)
    assert not (tmp_path / "refit").exists()


def test_a_cut_past_the_whole_gap_says_the_after_lies_under_the_floor():
    # review AX: "202 %" beside a held-out map of 0.207 -> 0.202 mm read as a bug; the
    # mean |residual| stood 0.011 mm above the floor before and fell under it after
    from calib.report.diagnosis import _cut_text

    assert _cut_text(0.5) == "50 %" and _cut_text(1.0) == "100 %" and _cut_text(None) is None
    assert _cut_text(2.02) == "202 % (after: under the floor)"


def test_a_noise_model_longer_than_its_variogram_is_said_to_blind_the_misfit_test():
    # review AX: "Misfit test (band F): p = 1, fits" beside "named: skin": the noise model
    # (51 mm, its variogram reaching 40 mm) had taken the skin's print for noise
    from calib.report.diagnosis import _caveats

    def doc(length_mm, at_bound=False):
        model = {"length_mm": length_mm, "max_lag_mm": 40.0, "length_at_bound": at_bound}
        return {"scans": {}, "noise": {"model": model}, "model_mesh": {}}

    (said,) = _caveats(doc(51.4))
    assert said.startswith("the noise model's correlation length (51 mm) reaches past the ")
    assert "variogram's 40 mm" in said and "cannot tell a smooth misfit from noise" in said
    assert _caveats(doc(12.0)) == [] and len(_caveats(doc(12.0, at_bound=True))) == 1


def test_an_empty_localisation_region_says_why_it_is_empty():
    # review BY, F15: "inclusions | 0 | – | – ..." for both scans, though the model had
    # three inclusions: no diagnosed point lay within the region's radius of one
    from calib.report.diagnosis import _localisation_table

    full = {"n": 12, "mean_mm": 0.1, "rms_mm": 0.2, "z": 2.5, "p_value": 0.01,
            "share_significant": 0.5}  # fmt: skip
    empty = dict.fromkeys(full, None) | {"n": 0}
    doc = {
        "scans": {"region_scale": 0.5, "rim_margin_mm": 7.0},
        "localisation": {"lat": {"regions": {"apex": full, "rim": empty, "inclusions": empty}}},
    }
    page = _localisation_table(doc)
    # the radii as diagnose labels the points: the regions' factor, the rim margin's floor
    # the regions are exclusive, apex first, then rim (review BZ, F2: a point near an
    # inclusion and the nipple is the apex's, so the row must not say none is near one)
    assert "no diagnosed point outside the apex and rim within 7.5 mm of an inclusion" in page
    assert "no diagnosed point outside the apex within 7 mm of the back plate" in page
    assert "–" not in page and "<td>12</td>" in page and "<td>0.01</td>" in page


def test_a_named_skin_says_its_c1_holds_for_the_model_s_skin_form_only():
    # measured on the independent generator's skin sets (README, "A skin hidden by the
    # other FE code"): another code's skin came out at ratio 3-4 against 8, and with a
    # stiff collar at the clamp c1 27 % low with a confident interval; the summary said
    # nothing of it
    from calib.report.diagnosis import _caveats

    base = {"scans": {}, "noise": {}, "model_mesh": {}}
    skin = base | {"named": ["skin"], "refit": {"intervals": {"skin": {"thickness_mm": 1.5}}}}
    (said,) = _caveats(skin)
    assert said.startswith("the skin is the model's band of 1.5 mm over every surface")
    assert "c1 27 % low" in said
    assert _caveats(base | {"named": ["poisson"], "refit": {"intervals": {}}}) == []
