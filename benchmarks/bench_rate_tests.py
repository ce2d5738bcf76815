"""Long-run rates of five of the default suite's seeded false-alarm tests (review CF 7-9).

Each such test draws a few hundred null residuals from a seed and bounds the share of
alarms by the nominal level plus three binomial standard errors. This script runs the
tests' own loops (their fixtures and helpers, imported from ``tests/calib``) with the
same seeds for many more draws, so a test's comment can say what its statistic's
long-run rate is (the chance that its bar passes a doubled rate is binomial arithmetic
on its draws, in its comment). Not covered: the 60-draw noisier-scan test of
``test_stats_scores.py``, whose bar is meant to catch a rate of 27-32 %.

    python benchmarks/bench_rate_tests.py [--draws 2000] [--only NAME,...]

Prints one row per rate: the test, the draws, the alarms, the rate and its binomial
95 % interval (Wilson).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from _provenance import print_header

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "calib"))


def _fixture(f):
    return f.__wrapped__()  # a pytest fixture's own function


def consistency(n):
    import test_stats_consistency as T

    sample, J, sampler = _fixture(T.setup)
    rng = np.random.default_rng(11)
    hits = [
        T._test(sample, J, T._calibrated(sample, J, sampler.draw(rng)[:, 0])[0], 0.05).verdict
        == "inconsistent"
        for _ in range(n)
    ]
    return {"test_stats_consistency::test_false_alarm_rate_on_correlated_null_residuals": hits}


def misfit(n):
    import test_stats_scores as T

    from calib.stats.noise import estimate_noise
    from calib.stats.scores import misfit_design, misfit_test

    sample, J, _, sampler = _fixture(T.setup)
    rng = np.random.default_rng(1)
    design = misfit_design(sample, J)
    hits = []
    for _ in range(n):
        r = T._residual(J, sampler.draw(rng)[:, 0])
        fit = estimate_noise(sample, r)
        res = misfit_test(r, J, sample, fit.best, alpha=0.05, alternatives=fit.plausible[1:],
                          design=design)  # fmt: skip
        hits.append(res.verdict == "misfit")
    return {"test_stats_scores::test_misfit_false_alarm_rate_on_correlated_noise": hits}


def screen(n):
    import test_stats_scores as T

    sample, J, sampler, S = _fixture(T.correlated)
    rng = np.random.default_rng(3)
    p, fw = [], []
    for _ in range(n):
        res = T._screen_refitted(sampler.draw(rng)[:, 0], sample, J, S, quantile="satterthwaite",
                                 directions=[1, -1, 0])  # fmt: skip
        p.append([e.p_value for e in res.effects])
        fw.append(any(e.significant for e in res.effects))
    p = np.array(p)
    joint = [np.nanmin(T._effect_holm(list(q), ["smooth", "smooth", "bump"])) < 0.05 for q in p]
    name = "test_stats_scores::test_screening_false_positive_rate_on_correlated_null_residuals"
    out = {f"{name} (family-wise)": fw, f"{name} (two effects)": joint}
    two = np.column_stack([2 * np.minimum(p[:, :2], 1 - p[:, :2]), p[:, 2]])
    for k, col in enumerate(("p2", "tilt", "bump")):
        out[f"{name} ({col})"] = list(p[:, k] < 0.05)
        if k < 2:  # one-sided columns: their two-sided p, which the test holds alike
            out[f"{name} ({col}, two-sided)"] = list(two[:, k] < 0.05)
    return out


def diagnose(n):
    import test_diagnose as T

    sample, J, cols, sampler = _fixture(T.linear)
    offset = np.where(sample.scan == 0, 0.1, -0.05)
    rng = np.random.default_rng(7)
    fw, raw, mis = [], [], []
    for _ in range(n):
        r = T._at_fit(J, sampler.draw(rng)[:, 0] + offset)
        s = T.screen(T._fields(sample, r, J, cols), T._points(sample), alpha=0.05)
        fw.append(any(e.significant for e in s.screening.effects))
        raw.append([e.p_value < 0.05 for e in s.screening.effects])
        mis.append(s.misfit.verdict == "misfit")
    name = "test_diagnose::test_screening_false_positive_rate_on_correlated_null_residuals"
    out = {f"{name} (family-wise)": fw, f"{name} (misfit)": mis}
    for k, col in enumerate(cols):
        out[f"{name} ({col})"] = [row[k] for row in raw]
    return out


def absorbed(n):
    import test_diagnose as T

    from calib.stats.coverage import misfit_pattern

    sample, J, cols, sampler = _fixture(T.linear)
    _, y, z = sample.points_mm.T
    other = y * z - np.mean(y * z)
    shape = misfit_pattern(sample, kind="tilt") + other / np.sqrt(np.mean(other**2))
    shape = shape / np.sqrt(np.mean(shape**2))
    rng = np.random.default_rng(12)
    fw = []
    for _ in range(n):
        r = T._at_fit(J, sampler.draw(rng)[:, 0] + 0.2 * shape)
        f = T._with_discretisation(T._fields(sample, r, J, cols), sample, shape)
        fw.append(any(e.significant for e in T.screen(f, T._points(sample), alpha=0.05)
                      .screening.effects))  # fmt: skip
    name = (
        "test_diagnose::test_with_the_model_mesh_s_error_absorbed_the_false_positive_rate_is_held"
    )
    return {f"{name} (absorbed, family-wise)": fw}


RUNS = {"consistency": consistency, "misfit": misfit, "screen": screen, "diagnose": diagnose,
        "absorbed": absorbed}  # fmt: skip


def _wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    p = k / n
    mid, half = p + z * z / (2 * n), z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (mid - half) / (1 + z * z / n), (mid + half) / (1 + z * z / n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--only", default=",".join(RUNS), help="comma-separated: " + ", ".join(RUNS))
    args = ap.parse_args()
    only = [w for w in args.only.split(",") if w]
    bad = sorted(set(only) - set(RUNS))
    if bad:
        ap.error(f"--only: unknown {bad}; expected some of {', '.join(RUNS)}")
    print_header()
    print("| test (statistic) | draws | alarms | rate | 95 % interval | s per draw |")
    print("|---|---:|---:|---:|---|---:|")
    for what in only:
        t0 = time.perf_counter()
        rows = RUNS[what](args.draws)
        per = (time.perf_counter() - t0) / args.draws
        for name, hits in rows.items():
            k = int(np.sum(hits))
            lo, hi = _wilson(k, len(hits))
            print(f"| {name} | {len(hits)} | {k} | {k / len(hits):.2%} | "
                  f"{lo:.2%}-{hi:.2%} | {per:.3f} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
