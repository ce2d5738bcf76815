"""The mesh check's interval arithmetic, its grid-convergence index from two or three meshes
and its fallback to a finer mesh (no FE here)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from calib.fitting import meshcheck
from calib.fitting import pipeline as run
from calib.fitting.meshcheck import CheckMesh, MeshCheck, combined_ci95, grid_convergence
from calib.fitting.options import check_mesh_check_ratio, mesh_check_ratios, parse_mesh_check


def test_combined_interval_adds_in_quadrature():
    # 1.96 se = 0.03 and GCI = 0.04 in ln c1 give a half-width of exactly 0.05
    lo, hi = combined_ci95(400.0, 0.03 / 1.96, 0.04)
    assert np.log(hi / 400.0) == pytest.approx(0.05, rel=1e-12)
    assert np.log(400.0 / lo) == pytest.approx(0.05, rel=1e-12)


@pytest.mark.parametrize("ratio", [0.4, 1.0, 1.05, 3.5])
def test_bad_ratios_are_refused(ratio):
    from calib.fitting import OptionsError

    with pytest.raises(
        OptionsError, match=r"^mesh_check_ratio \(--mesh-check\) must lie"
    ):  # a ValueError too
        check_mesh_check_ratio(ratio)


def test_a_failed_coarse_check_falls_back_to_a_finer_mesh(monkeypatch):
    calls = []

    def fake_check(cal, theta, *, ratio, progress=None):
        (ratio,) = mesh_check_ratios(ratio)  # one check mesh at a time
        calls.append(ratio)
        size = cal.options.mesh_size_mm
        if ratio > 1:
            return MeshCheck(size, size * ratio, 100, None, None, "ConvergenceError: test")
        return MeshCheck(size, size * ratio, 900, 410.0, 0.04)

    monkeypatch.setattr(run, "mesh_check", fake_check)
    cal = SimpleNamespace(options=SimpleNamespace(mesh_size_mm=14.0, mesh_check_ratio=1.4))
    unc = SimpleNamespace(c1_ci95_pa=(395.0, 405.0), se_ln_c1=0.03 / 1.96, interval=None)
    said = []
    check, ci = run._mesh_check(cal, np.log(400.0), unc, said.append)
    assert calls == [1.4, pytest.approx(1 / 1.4)]
    assert check.check_mesh_size_mm == pytest.approx(10.0)
    assert any("failed" in s and "10.0 mm" in s for s in said)
    assert ci == pytest.approx(combined_ci95(400.0, unc.se_ln_c1, 0.04))


def test_a_check_that_fails_both_ways_keeps_the_noise_interval(monkeypatch):
    def failing(cal, theta, *, ratio, progress=None):
        (ratio,) = mesh_check_ratios(ratio)
        return MeshCheck(14.0, 14.0 * ratio, 0, None, None, "MeshError: test")

    monkeypatch.setattr(run, "mesh_check", failing)
    cal = SimpleNamespace(options=SimpleNamespace(mesh_size_mm=14.0, mesh_check_ratio=1.4))
    unc = SimpleNamespace(c1_ci95_pa=(395.0, 405.0), se_ln_c1=0.01)
    said = []
    check, ci = run._mesh_check(cal, np.log(400.0), unc, said.append)
    assert ci == (395.0, 405.0) and check.failure == "MeshError: test"
    assert "noise only" in said[-1]


def test_one_residual_leaves_the_noise_unknown():
    # The nipple objective has one residual for one parameter: no degree of freedom remains
    # to estimate the noise, so no interval is claimed (it printed 0 - 3e51 Pa before).
    from calib.fitting.uncertainty import gauss_newton_uncertainty

    unc = gauss_newton_uncertainty(
        420.0, np.array([0.44]), np.array([0.1]), np.zeros((1, 3)), area_mm2=None
    )
    assert unc.se_ln_c1 is None and unc.c1_ci95_pa is None
    cal = SimpleNamespace(options=SimpleNamespace(mesh_size_mm=14.0, mesh_check_ratio=1.4))
    check, ci = run._mesh_check(cal, np.log(420.0), unc, lambda msg: None)
    assert check is None and ci is None


# ln c1(h) = L + C h^p on three meshes h0 r, h0, h0 / r: the three-mesh check must observe
# p and bound the calibration mesh's error C h0^p by Richardson's estimate x 1.25, exactly
# (to rounding: 1e-9).
@pytest.mark.parametrize("order", [0.8, 1.6, 2.0, 3.5])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_three_meshes_observe_the_order_of_a_power_law(order, sign):
    L, C, h0, r = np.log(420.0), sign * 4e-5, 12.0, 1.4
    ln_c1 = lambda h: L + C * h**order  # noqa: E731
    gci, p, fs, how = grid_convergence(ln_c1(h0), [(r, ln_c1(h0 * r)), (1 / r, ln_c1(h0 / r))])
    assert how == "observed order" and fs == 1.25
    assert p == pytest.approx(order, rel=1e-9)
    assert gci == pytest.approx(1.25 * abs(C) * h0**order, rel=1e-9)


def test_one_check_mesh_uses_the_assumed_order():
    # Richardson with p = 1.6 on a sequence whose true order is 1.6: the error exactly
    L, C, h0 = np.log(420.0), 3e-5, 12.0
    gci, p, fs, how = grid_convergence(L + C * h0**1.6, [(1.4, L + C * (1.4 * h0) ** 1.6)])
    assert (p, fs, how) == (1.6, 1.25, "assumed order")
    assert gci == pytest.approx(1.25 * C * h0**1.6, rel=1e-9)


@pytest.mark.parametrize(
    "c1_coarse, c1_fine, why",
    [
        # the dissertation twin's 16.8 / 12 / 8.6 mm model meshes: the change grows under
        # refinement (observed order -7.6)
        (413.8, 419.4, "diverging"),
        (418.0, 419.4, "oscillating"),  # the two changes have opposite signs
        (414.19, 419.4, "order above 4"),  # p = 14
    ],
)
def test_irregular_convergence_gets_three_times_the_spread(c1_coarse, c1_fine, why):
    ln0 = np.log(414.2)
    gci, p, fs, how = grid_convergence(ln0, [(1.4, np.log(c1_coarse)), (1 / 1.4, np.log(c1_fine))])
    assert how == "not asymptotic", why
    spread = np.log(max(c1_coarse, c1_fine, 414.2) / min(c1_coarse, c1_fine, 414.2))
    assert fs == 3.0 and gci == pytest.approx(3.0 * spread, rel=1e-12)


def test_the_dissertation_twins_three_meshes_would_have_covered_its_truth():
    # what the default coarser check missed (docs/calibration-evidence.md: 414.2 Pa, truth
    # 420 Pa, noise half-width 0.86 %): with the finer mesh the bound holds the truth
    ln0 = np.log(414.2)
    gci, *_ = grid_convergence(ln0, [(1.4, np.log(413.8)), (1 / 1.4, np.log(419.4))])
    lo, hi = combined_ci95(414.2, 0.0086 / 1.96, gci)
    assert lo < 420.0 < hi
    gci_coarse, *_ = grid_convergence(ln0, [(1.4, np.log(413.8))])
    assert not combined_ci95(414.2, 0.0086 / 1.96, gci_coarse)[1] > 420.0


def test_two_check_meshes_must_be_reciprocal():
    with pytest.raises(ValueError, match="reciprocal"):
        grid_convergence(0.0, [(1.4, 0.0), (0.8, 0.0)])
    with pytest.raises(ValueError, match="coarser r and a finer 1/r"):
        parse_mesh_check("1.4,0.8")
    with pytest.raises(ValueError, match="1.4,0.714"):
        parse_mesh_check("fine")
    assert parse_mesh_check("1.4,0.714") == (1.4, 0.714)
    assert parse_mesh_check("0") == 0.0


def test_a_three_mesh_check_keeps_the_mesh_that_solved(monkeypatch):
    # the finer mesh fails: the coarser one bounds the error with the assumed order, and
    # the failure is in the result
    def check_at(cal, theta, ratio):
        size = 12.0 * ratio
        if ratio < 1:
            return CheckMesh(ratio, size, 0, None, "ConvergenceError: test")
        return CheckMesh(ratio, size, 900, 410.0)

    monkeypatch.setattr(meshcheck, "_check_at", check_at)
    cal = SimpleNamespace(
        options=SimpleNamespace(mesh_size_mm=12.0, mesh_check_ratio=(1.4, 1 / 1.4))
    )
    unc = SimpleNamespace(c1_ci95_pa=(395.0, 405.0), se_ln_c1=0.01, interval=None)
    said = []
    check, ci = run._mesh_check(cal, np.log(400.0), unc, said.append)
    assert [m.mesh_size_mm for m in check.meshes] == pytest.approx([16.8, 12 / 1.4])
    assert check.convergence == "assumed order" and "8.6 mm: ConvergenceError" in check.failure
    expected, *_ = grid_convergence(np.log(400.0), [(1.4, np.log(410.0))])
    assert check.gci_ln_c1 == pytest.approx(expected)
    assert ci == pytest.approx(combined_ci95(400.0, 0.01, expected))
    assert any("8.6 mm mesh failed" in s for s in said)


def _doc(check: dict | None) -> dict:
    unc = {"c1_ci95_pa": [423.2, 432.2], "mesh_check": check}
    return {"uncertainty": unc}


@pytest.mark.parametrize(
    "convergence, says, warns",
    [
        ("observed order", "(observed order 1.15)", None),
        ("not asymptotic", "(not asymptotic)", "does not converge regularly"),
        ("assumed order", "(assumed order 1.60)", "--mesh-check 1.4,0.714 observes"),
    ],
)
def test_the_printed_summary_names_the_kind_of_bound(convergence, says, warns):
    from calib.report.tables import _uncertainty_lines

    meshes = [
        {"ratio": 1.4, "mesh_size_mm": 16.8, "tets": 1, "c1_pa": 422.7, "failure": ""},
        {"ratio": 0.714, "mesh_size_mm": 8.6, "tets": 1, "c1_pa": None, "failure": "MeshError: x"},
    ]
    check = {
        "check_mesh_size_mm": 16.8,
        "c1_check_pa": 422.7,
        "gci_ln_c1": 0.031,
        "failure": "",
        "order": 1.15 if convergence == "observed order" else 1.6,
        "convergence": convergence,
        "meshes": meshes,
    }
    lines = _uncertainty_lines(_doc(check)["uncertainty"], "surface")
    text = "\n".join(lines)
    assert "16.8 mm mesh calibrates to 422.7 Pa" in text
    assert "8.6 mm mesh failed: MeshError: x" in text
    assert f"GCI) 3.1 % {says}" in text
    if warns is None:  # an observed order in range: no warning (review AA: was vacuous)
        assert "does not converge" not in text and "observes" not in text
    else:
        assert warns in text


def test_a_calibration_json_of_0_1_still_prints():
    # records written before the three-mesh check have no meshes/convergence keys
    check = {
        "check_mesh_size_mm": 16.8,
        "c1_check_pa": 422.7,
        "gci_ln_c1": 0.01,
        "failure": "",
        "order": 1.6,
        "safety_factor": 1.25,
    }
    from calib.report.tables import _uncertainty_lines

    text = "\n".join(_uncertainty_lines(_doc(check)["uncertainty"], "surface"))
    assert "16.8 mm mesh calibrates to 422.7 Pa" in text and "assumed order 1.60" in text


@pytest.mark.parametrize("ratios", [(1.4,), (1.4, 1 / 1.4)])
def test_a_bound_carried_to_another_size_is_the_bound_a_check_there_finds(ratios):
    # two code paths on ln c1(h) = L + C h^p (the module's model, exact here): the bound
    # a check at 12 mm carries to 15 mm is the one a check run at 15 mm finds; with one
    # check mesh at the assumed order, with two at the observed one (p = 2.3 here)
    from calib.fitting.meshcheck import gci_at_size

    p = meshcheck.OBSERVED_ORDER if len(ratios) == 1 else 2.3

    def ln_c1(h):
        return np.log(420.0) + 0.002 * h**p

    def checked(h):
        gci, order, _, how = grid_convergence(ln_c1(h), [(q, ln_c1(q * h)) for q in ratios])
        return {"gci_ln_c1": gci, "order": order, "convergence": how, "mesh_size_mm": h}

    assert gci_at_size(checked(12.0), 15.0) == pytest.approx(checked(15.0)["gci_ln_c1"], rel=1e-9)
    assert gci_at_size(checked(12.0), 12.0) == pytest.approx(checked(12.0)["gci_ln_c1"], rel=1e-12)
    # the anomalous bound (3 x the data range) has no order: widened, never narrowed
    anomalous = checked(12.0) | {"convergence": "not asymptotic", "order": float("nan")}
    assert gci_at_size(anomalous, 24.0) == pytest.approx(
        anomalous["gci_ln_c1"] * 2**meshcheck.OBSERVED_ORDER
    )
    assert gci_at_size(anomalous, 6.0) == anomalous["gci_ln_c1"]
    assert gci_at_size({"gci_ln_c1": None, "mesh_size_mm": 12.0}, 14.0) is None
    with pytest.raises(ValueError, match="positive mesh sizes, got 0 mm"):
        gci_at_size({"gci_ln_c1": 0.02}, 14.0)
