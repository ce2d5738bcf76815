"""Calibration: analytic gradient vs finite differences, and recovery of a known c1.

The measurements here come straight from FE solves of a homogeneous truth (no imaging),
so the only error between model and truth is the model's remeshing/discretisation.
"""

from __future__ import annotations

import numpy as np
import pytest

import fem
from calib.data.measurements import Measurements, ScanMeasurement
from calib.fitting.meshcheck import combined_ci95, mesh_check
from calib.fitting.objective import Calibrator
from calib.fitting.optimise import _start, optimise
from calib.fitting.options import CalibrationOptions
from calib.fitting.pipeline import _measured_area_mm2
from calib.fitting.uncertainty import gauss_newton_uncertainty
from fem.geometry import PhantomSpec, build_phantom
from fem.meshing import mesh_phantom

C1_TRUE = 420.0
G_REF = np.array([1.0, 0.0, 0.0])
# Calibrate on a 50 deg tilt: the shortcut's "2 x gravity" between lateral postures
# inverts elements of coarse test meshes (see the closing notes); validate on right lateral.
G_CAL = np.array([np.cos(np.radians(50)), 0.0, np.sin(np.radians(50))])
G_VAL = np.array([-1.0, 0.0, 0.0])


def _surface(mesh: fem.TetMesh, positions: np.ndarray):
    faces = fem.boundary_faces(mesh.tets)
    used = np.unique(faces)
    remap = np.full(mesh.n_nodes, -1)
    remap[used] = np.arange(len(used))
    v = positions[used]
    return v, remap[faces], np.abs(mesh.nodes_mm[used, 2]) < 1e-6


@pytest.fixture(scope="module")
def measurements() -> Measurements:
    ph = build_phantom(PhantomSpec(resolution_mm=12.0, n_inclusions=0, seed=3))
    mesh = mesh_phantom(ph, size_mm=12.0)
    model = fem.Model.homogeneous(mesh, fem.NeoHookean(C1_TRUE, nu=0.499))
    disc = fem.discretize(mesh, model.support)
    scans = {}
    tumour = np.array([5.0, 0.0, 25.0])
    for name, role, g in (("ref", "reference", G_REF), ("cal", "calibration", G_CAL),
                          ("val", "validation", G_VAL)):  # fmt: skip
        sol = fem.solve(model, gravity=g, disc=disc)
        pos = mesh.nodes_mm + sol.displacement_mm
        v, f, back = _surface(mesh, pos)
        nip = int(mesh.node_set("nipple")[0])
        t = tumour + fem.displacement_at(disc, sol.state, tumour[None])[0]
        scans[name] = ScanMeasurement(name, role, g, v, f, back, pos[nip], t, np.zeros(3),
                                      np.array([0.0, 0.0, -1.0]), np.eye(4))  # fmt: skip
    return Measurements(scans["ref"], scans)


@pytest.mark.parametrize(
    ("reference_state", "objective"),
    [
        ("shortcut", "surface"),
        pytest.param("unload", "surface", marks=pytest.mark.slow),
        pytest.param("unload", "landmarks", marks=pytest.mark.slow),
    ],
)
def test_gradient_matches_central_differences(measurements, reference_state, objective):
    opts = CalibrationOptions(objective=objective, reference_state=reference_state,
                              mesh_size_mm=12.0, max_points=800)  # fmt: skip
    cal = Calibrator(measurements, opts)
    theta = np.log(380.0)
    _, g = cal.objective(np.array([theta]))
    h = 3e-4
    jp, _ = cal.objective(np.array([theta + h]))
    jm, _ = cal.objective(np.array([theta - h]))
    fd = (jp - jm) / (2 * h)
    # central differences are O(h^2) ~ 1e-7 relative here; the issue asks for 1e-4, and
    # both the FE solves (rtol 1e-8) and the inverse-Newton unloading are far tighter.
    # The closest-point residuals are piecewise smooth: a point that switches triangle
    # between theta +- h adds an O(h) kink (measured 2e-4 relative at h = 1e-3 on one
    # mesh, 3e-8 at h = 3e-4), so h is kept small; below ~1e-4 solver noise dominates.
    assert g[0] == pytest.approx(fd, rel=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("reference_state", ["unload"])
def test_recovers_known_c1(measurements, reference_state):
    opts = CalibrationOptions(objective="surface", reference_state=reference_state,
                              mesh_size_mm=12.0, max_points=1500, profile_points=0)  # fmt: skip
    cal = Calibrator(measurements, opts)
    theta0 = _start(cal, lambda msg: None)
    theta, _, status = optimise(cal, lambda msg: None, theta0)
    assert status.success, status
    # the bar: within 3 % of the truth for a homogeneous truth; the model mesh is
    # a remeshed copy of the truth's loaded surface, so a small discretisation bias remains
    assert np.exp(theta) == pytest.approx(C1_TRUE, rel=0.03)
    res = cal.residuals(theta, cal.calibration_scans, gradient=True)
    r = np.concatenate([v.r for v in res.values()])
    # mm: the remeshing error of a 12 mm surface, measured 0.084 mm; the bar twice that
    assert np.sqrt(np.mean(r**2)) < 0.17
    # Here the model error is discretisation alone, so the 95 % interval with the grid
    # convergence check must contain the truth (issue 6), and the check's GCI must bound the
    # error it estimates: measured |ln(c1 / 420)| 0.0083 against a GCI of 0.039, where the
    # noise-only interval (422.5-424.5 Pa) misses the truth (review CF-4: "the check
    # widens the interval" held by construction, hypot(crit se, gci) > crit se).
    dr = np.concatenate([v.dr for v in res.values()])
    pts = np.concatenate([v.points_mm for v in res.values()])
    unc = gauss_newton_uncertainty(np.exp(theta), r, dr, pts, area_mm2=_measured_area_mm2(cal))
    check = mesh_check(cal, theta)
    assert check.gci_ln_c1 is not None, check.failure
    crit = unc.interval["critical_value"]  # as the pipeline combines them
    lo, hi = combined_ci95(float(np.exp(theta)), unc.se_ln_c1, check.gci_ln_c1, critical_value=crit)
    assert lo <= C1_TRUE <= hi, (lo, hi, unc.c1_ci95_pa, check)
    assert abs(theta - np.log(C1_TRUE)) <= check.gci_ln_c1, (theta, check)


# the shortcut's column is slow (22 s in CI): for the default suite's budget (~15 min) its
# derivative is checked there through the objective's gradient
# (test_gradient_matches_central_differences[shortcut-surface]); `make test-all` runs both
@pytest.mark.parametrize(
    "reference_state", ["unload", pytest.param("shortcut", marks=pytest.mark.slow)]
)
def test_position_sensitivities_match_central_differences(reference_state):
    """d(positions)/d ln c1 of every posture, through the reference recovery (fast case).

    The model mesh is the truth's own loaded mesh, so inverse-Newton unloading is exact
    (to the Newton tolerance) and central differences are limited by O(h^2) only.
    """
    from calib.model.forward import ForwardModel

    ph = build_phantom(PhantomSpec(resolution_mm=16.0, n_inclusions=0, seed=1))
    mesh = mesh_phantom(ph, size_mm=16.0)
    model = fem.Model.homogeneous(mesh, fem.NeoHookean(C1_TRUE, nu=0.499))
    loaded = mesh.with_nodes(mesh.nodes_mm + fem.solve(model, gravity=G_REF).displacement_mm)
    gravities = {"cal": G_CAL, "val": G_VAL}

    def positions(theta, gradient):
        fm = ForwardModel(loaded, G_REF, reference_state=reference_state)
        return fm.evaluate(theta, gravities, gradient=gradient)

    theta, h = np.log(400.0), 1e-3
    exact = positions(theta, True)
    plus, minus = positions(theta + h, False), positions(theta - h, False)
    for name in gravities:
        fd = (plus[name].positions_mm - minus[name].positions_mm) / (2 * h)
        # O(h^2) truncation ~1e-6 relative; Newton tolerances (rtol 1e-8) far below
        err = np.abs(exact[name].dpositions_mm - fd).max() / np.abs(fd).max()
        assert err < 1e-4
