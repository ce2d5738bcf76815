"""The mesh check's interval arithmetic and its fallback to a finer mesh (no FE here)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from calib.fitting import pipeline as run
from calib.fitting.meshcheck import MeshCheck, combined_ci95
from calib.fitting.options import check_mesh_check_ratio


def test_combined_interval_adds_in_quadrature():
    # 1.96 se = 0.03 and GCI = 0.04 in ln c1 give a half-width of exactly 0.05
    lo, hi = combined_ci95(400.0, 0.03 / 1.96, 0.04)
    assert np.log(hi / 400.0) == pytest.approx(0.05, rel=1e-12)
    assert np.log(400.0 / lo) == pytest.approx(0.05, rel=1e-12)


@pytest.mark.parametrize("ratio", [0.4, 1.0, 1.05, 3.5])
def test_bad_ratios_are_refused(ratio):
    with pytest.raises(ValueError, match="mesh check ratio"):
        check_mesh_check_ratio(ratio)


def test_a_failed_coarse_check_falls_back_to_a_finer_mesh(monkeypatch):
    calls = []

    def fake_check(cal, theta, *, ratio):
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
    def failing(cal, theta, *, ratio):
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

    unc = gauss_newton_uncertainty(420.0, np.array([0.44]), np.array([0.1]), np.zeros((1, 3)),
                                   area_mm2=None)  # fmt: skip
    assert unc.se_ln_c1 is None and unc.c1_ci95_pa is None
    cal = SimpleNamespace(options=SimpleNamespace(mesh_size_mm=14.0, mesh_check_ratio=1.4))
    check, ci = run._mesh_check(cal, np.log(420.0), unc, lambda msg: None)
    assert check is None and ci is None
