"""The optimiser: Gauss-Newton steps, backtracking on failed FE solves, honest status.

A stand-in calibrator with a closed-form least-squares objective (no FE): residuals
``r_i = a_i (theta - theta*) + e_i`` give ``J``, ``g`` and the Gauss-Newton curvature
exactly, and a chosen region of theta "fails" as an FE solve would.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import fem
from calib.fitting.objective import EvaluationFailed
from calib.fitting.optimise import EDGE_TOLERANCE, optimise


class Quadratic:
    def __init__(
        self, theta_star, *, fail=lambda theta: False, curvature_scale=1.0, stage="posture"
    ):
        rng = np.random.default_rng(0)
        self.stage = stage  # what a failed evaluation says failed
        self.a = rng.uniform(5.0, 15.0, 200)  # mm per unit ln c1, like surface sensitivities
        self.e = rng.normal(0.0, 0.1, 200)
        self.theta_star, self.fail = theta_star, fail
        self.k = curvature_scale  # the Gauss-Newton curvature is off by this factor
        self.history: list[dict] = []
        self.options = SimpleNamespace(max_iterations=30)
        self.gauss_newton_curvature = 1.0
        self.first_estimate_from_guess = False  # as Calibrator after its first estimate

    def objective(self, theta_arr):
        theta = float(theta_arr[0])
        if self.fail(theta):
            self.history.append({"c1_pa": float(np.exp(theta)), "objective": None, "failed": True})
            raise EvaluationFailed("test", stage=self.stage)
        r = self.a * (theta - self.theta_star) + self.e
        J, g = 0.5 * float(np.mean(r**2)), float(np.mean(r * self.a))
        self.gauss_newton_curvature = self.k * float(np.mean(self.a**2))
        self.history.append(
            {
                "c1_pa": float(np.exp(theta)),
                "objective": J,
                "gradient": g,
                "rms_mm": 0.0,
                "wall_s": 0.0,
            }
        )
        return J, np.array([g])

    def minimiser(self):  # closed form of the linear least squares
        return self.theta_star - float(np.sum(self.a * self.e) / np.sum(self.a**2))


def test_converges_to_the_closed_form_minimum():
    cal = Quadratic(np.log(420.0))
    theta, J, status = optimise(cal, lambda msg: None, np.log(600.0))
    # a linear residual: one Gauss-Newton step is exact (to round-off)
    assert theta == pytest.approx(cal.minimiser(), abs=1e-9)
    assert status.success and status.bound is None and status.failed_evaluations == 0
    assert status.evaluations <= 3


def test_a_failed_solve_halves_the_step_and_is_recorded():
    # the FE "fails" below 450 Pa (a soft phantom that cannot carry the load); the minimum
    # lies at 460 Pa, so the first full step (from 800 Pa to ~460) must be retried shorter
    # if it overshoots into the failing region, and the failures stay in the history
    cal = Quadratic(np.log(460.0), fail=lambda t: np.exp(t) < 450.0, curvature_scale=0.4)
    said = []
    theta, _, status = optimise(cal, said.append, np.log(800.0))
    assert status.failed_evaluations >= 1
    assert any("no FE solution" in s for s in said)
    # each retry from 800 Pa is half the step before it (here 201 Pa, 401 Pa, then 566 Pa
    # solved): review CF-23, the halving had not been checked
    ln_c1 = np.log([h["c1_pa"] for h in cal.history[:4]])
    steps = ln_c1[1:] - ln_c1[0]
    assert cal.history[1].get("failed") and cal.history[2].get("failed")
    assert steps[1:] == pytest.approx([steps[0] / 2, steps[0] / 4], rel=1e-9)
    # the stopping rule leaves a step below 1e-3 / sqrt(H) = 1.5e-4 in ln c1, off by at most
    # the curvature's factor 1 / 0.4 here: 3.7e-4 (measured 0: the last step is exact)
    assert theta == pytest.approx(cal.minimiser(), abs=4e-4)
    assert status.success, status


def test_a_minimum_where_the_fe_model_has_no_solution_stops_at_the_edge_unconverged():
    # A clamped model of a plate that slipped: its minimum (380 Pa) lies below 400 Pa,
    # where (here by fiat) no FE solution exists. Each failed c1 becomes a wall that
    # later steps stop halfway to, so the iteration closes in on the edge instead of
    # failing at the Gauss-Newton target on every iteration, and it says why it stopped.
    edge = np.log(400.0)
    cal = Quadratic(np.log(380.0), fail=lambda t: t < edge)
    said = []
    theta, _, status = optimise(cal, said.append, np.log(500.0))
    assert not status.success and status.bound is None
    assert "no solution" in status.message
    # stopped within EDGE_TOLERANCE (1 % in c1) of a failed c1 at or below the edge, the
    # best solvable point above it; a failed trial is never repeated
    assert np.log(status.unsolved_c1_pa) < edge <= theta
    assert theta - np.log(status.unsolved_c1_pa) < 2 * EDGE_TOLERANCE
    tried = [h["c1_pa"] for h in cal.history if h.get("failed")]
    assert len(tried) == len(set(tried)) == status.failed_evaluations
    # the walls halve the distance to the edge: about log2(5 % / 1 %) ~ 2-3 failures
    # from the first one at the target, not several per iteration (without walls: 17
    # failed of 22 evaluations, stopped by the line search; here 2 of 6)
    assert status.failed_evaluations <= 4, tried
    assert status.to_json()["unsolved_c1_pa"] == status.unsolved_c1_pa


def test_a_minimum_beyond_the_bounds_is_not_called_a_success():
    cal = Quadratic(np.log(5000.0))  # far above 4 x the start
    theta, _, status = optimise(cal, lambda msg: None, np.log(500.0))
    assert theta == pytest.approx(np.log(2000.0), abs=1e-9)
    assert not status.success and status.bound == "upper"
    assert "upper bound" in status.message


def test_no_solution_along_the_whole_step_stops_at_the_edge_it_found():
    # the edge (499 Pa) lies within 1/64 of the first step from 500 Pa: every trial of
    # the line search fails, and the stop reports the nearest failed c1 and what failed
    # there (review R: it reported "no point that decreases J" and no edge, so a
    # calibration could not tell where its model stopped solving)
    edge = np.log(499.0)
    cal = Quadratic(np.log(300.0), fail=lambda t: t < edge, stage="stress-free reference")
    theta, _, status = optimise(cal, lambda msg: None, np.log(500.0))
    assert theta == pytest.approx(np.log(500.0)) and not status.success
    assert "no solution" in status.message and status.failed_evaluations >= 6
    tried = [np.log(h["c1_pa"]) for h in cal.history if h.get("failed")]
    assert np.log(status.unsolved_c1_pa) == pytest.approx(max(tried), abs=1e-12)  # nearest
    assert np.log(status.unsolved_c1_pa) < edge
    assert status.unsolved_stage == "stress-free reference"
    assert status.to_json()["unsolved_stage"] == "stress-free reference"


def test_a_line_search_that_solved_a_trial_reports_no_edge():
    # a Gauss-Newton curvature 10x too flat overshoots to ~220 Pa, which solves but does
    # not decrease J; the shorter trials back towards 500 Pa fail (300-499.5 Pa here):
    # that is no edge next to the start (review S: an edge was reported, and with the
    # stress-free stage it would have run the whole fit again on curved elements)
    cal = Quadratic(
        np.log(460.0),
        curvature_scale=0.1,
        fail=lambda t: np.log(300.0) < t < np.log(499.5),
        stage="stress-free reference",
    )
    theta, _, status = optimise(cal, lambda msg: None, np.log(500.0))
    solved = [h["c1_pa"] for h in cal.history[1:] if not h.get("failed")]
    assert solved and min(solved) < 300.0  # the premise: the long trial solved
    assert status.failed_evaluations >= 1 and not status.success
    assert "line search" in status.message
    assert status.unsolved_c1_pa is None and status.unsolved_stage is None


def test_the_evaluation_failures_survive_a_process_pool():
    # a worker's exception is pickled back to the parent
    import pickle

    from calib.model.forward import ReferenceRecoveryFailed

    exc = pickle.loads(pickle.dumps(EvaluationFailed("no FE solution", stage="posture")))
    assert isinstance(exc, EvaluationFailed) and exc.stage == "posture"
    assert str(exc) == "no FE solution"
    exc = pickle.loads(pickle.dumps(ReferenceRecoveryFailed("not recovered", method="newton")))
    assert isinstance(exc, ReferenceRecoveryFailed) and exc.method == "newton"


def test_a_step_a_failed_trial_shortened_is_not_taken_for_convergence():
    # the minimum (497.5 Pa) lies beyond an edge at 499.95 Pa, 0.01 % from the start:
    # the line search halves down to a step shorter than the tolerance that lands
    # between the two; that says nothing of a minimum (review R: it was reported as
    # converged at 499.96 Pa with 6 of 8 evaluations failed)
    edge = np.log(499.95)
    cal = Quadratic(np.log(497.5), fail=lambda t: t < edge)
    theta, _, status = optimise(cal, lambda msg: None, np.log(500.0))
    assert theta >= edge and status.failed_evaluations >= 1
    assert not status.success, status
    assert np.log(status.unsolved_c1_pa) < edge and status.unsolved_stage == "posture"
    # the premise: a solved trial closer to the start than the tolerance (a short step)
    near = [np.log(h["c1_pa"]) for h in cal.history[1:] if not h.get("failed")]
    assert min(np.log(500.0) - t for t in near) < 1e-3 / np.sqrt(float(np.mean(cal.a**2)))


def test_an_overshooting_step_is_shortened_by_interpolation():
    # A Gauss-Newton curvature 10x too small (the nipple objective's: its residual does
    # not vanish at the optimum) overshoots the minimum 10-fold. Halving needs four
    # trials per iteration and lands off the minimum every time (the tiny twin's nipple
    # calibration: 35 evaluations); the quadratic through J(0), J'(0) and the rejected
    # trial is exact on this least-squares objective, so one backtrack lands on it.
    cal = Quadratic(np.log(460.0), curvature_scale=0.1)
    theta, _, status = optimise(cal, lambda msg: None, np.log(600.0))
    assert theta == pytest.approx(cal.minimiser(), abs=1e-9)
    assert status.success and status.evaluations == 3


def test_the_backtracking_step_is_safeguarded():
    from calib.fitting.optimise import _backtrack

    # the quadratic's minimiser, where it lies within [0.1, 0.5] of the rejected trial
    assert _backtrack(1.0, -1.0, 0.0) == pytest.approx(0.5)  # rise 0: curvature 1
    assert _backtrack(1.0, -1.0, 1.5) == pytest.approx(0.2)  # curvature 2.5
    assert _backtrack(1.0, -1.0, 100.0) == pytest.approx(0.1)  # far overshoot: 0.1
    assert _backtrack(0.5, -1.0, 0.1) == pytest.approx(0.25 / 1.2)  # curvature 0.6
    assert _backtrack(1.0, -1.0, -0.9) == pytest.approx(0.5)  # never longer than halving


def test_a_first_estimate_whose_postures_do_not_solve_tries_the_next_mesh_size(monkeypatch):
    # review AO's independent scans (a soft dome): the reference was recovered with
    # curved elements but no posture solved at the first estimate on the 12 mm mesh, and
    # the run ended there; the 16 mm mesh solved. Now the postures at the first estimate
    # are part of a mesh size's trial (their result cached for the optimiser)
    import calib.fitting.optimise as opt
    from calib.fitting import CalibrationOptions

    tried = []

    class Trial:
        def __init__(self, measurements, options, density_kg_m3):
            self.options, self.history = options, []
            tried.append(options.mesh_size_mm)
            self.mesh, self.calibration_scans = SimpleNamespace(n_tets=10), []

        def objective(self, theta):
            if self.options.mesh_size_mm == 12.0:
                raise EvaluationFailed("no FE solution at c1 = 300.0 Pa: load not applied")
            self.history.append({"c1_pa": 300.0, "rms_mm": 0.5, "wall_s": 1.0})
            return 1.0, np.array([0.0])

    monkeypatch.setattr(opt, "Calibrator", Trial)
    monkeypatch.setattr(opt, "_start", lambda cal, say: float(np.log(300.0)))
    monkeypatch.setattr(opt, "model_mesh_notes", lambda *a, **k: [])
    said = []
    measurements = SimpleNamespace(reference=SimpleNamespace(name="left_lateral"))
    cal, theta0, failed = opt.prepare(measurements, CalibrationOptions(), 1000.0, said.append)
    assert cal.options.mesh_size_mm == 14.0 and len(cal.history) == 1
    assert [f["mesh_size_mm"] for f in failed] == [12.0]
    assert (
        "no FE solution of the postures on the 12 mm model mesh at the first"
        in (failed[0]["failure"])
    )
    assert any("at the first estimate on the 12 mm model mesh" in s for s in said)

    # the last size's failure is the error, with its remedies
    def never(self, theta):
        raise EvaluationFailed("no FE solution at c1 = 300.0 Pa")

    monkeypatch.setattr(Trial, "objective", never)
    with pytest.raises(fem.ConvergenceError, match="16 mm model mesh .* try another --mesh-size"):
        opt.prepare(measurements, CalibrationOptions(), 1000.0, said.append)

    # each size is tried once (review AW: 14 mm asked for was tried again as a retry)
    tried.clear()
    with pytest.raises(fem.ConvergenceError, match="16 mm model mesh"):
        opt.prepare(measurements, CalibrationOptions(mesh_size_mm=14), 1000.0, said.append)
    assert tried == [14.0, 16.0]
    tried.clear()
    with pytest.raises(fem.ConvergenceError, match="14 mm model mesh"):
        opts = CalibrationOptions(mesh_size_mm=16, mesh_retry_mm=(14, 16, 14))
        opt.prepare(measurements, opts, 1000.0, said.append)
    assert tried == [16.0, 14.0]
