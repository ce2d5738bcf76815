"""Long-run rates of five of the default suite's seeded false-alarm tests (review CF 7-9).

Each such test draws a few hundred null residuals from a seed and bounds the share of
alarms by the nominal level plus three binomial standard errors. This script calls the
functions those tests draw through (``null_alarms`` and its kin, with the tests'
fixtures, imported from ``tests/calib``) with the same seeds for many more draws, so a
test's comment can say what its statistic's long-run rate is (the chance that its bar
passes a doubled rate is binomial arithmetic on its draws, in its comment). Not covered:
the 60-draw noisier-scan test of ``test_stats_scores.py``, whose bar is meant to catch a
rate of 27-32 %.

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


def _named(test: str, alarms: dict) -> dict:
    return {f"{test} ({name})": hits for name, hits in alarms.items()}


def consistency(n):
    import test_stats_consistency as T

    name = "test_stats_consistency::test_false_alarm_rate_on_correlated_null_residuals"
    return _named(name, T.null_alarms(_fixture(T.setup), n))


def misfit(n):
    import test_stats_scores as T

    name = "test_stats_scores::test_misfit_false_alarm_rate_on_correlated_noise"
    return _named(name, T.misfit_null_alarms(_fixture(T.setup), n))


def screen(n):
    import test_stats_scores as T

    name = "test_stats_scores::test_screening_false_positive_rate_on_correlated_null_residuals"
    return _named(name, T.screening_null_alarms(_fixture(T.correlated), n)[0])


def diagnose(n):
    import test_diagnose as T

    name = "test_diagnose::test_screening_false_positive_rate_on_correlated_null_residuals"
    return _named(name, T.screen_null_alarms(_fixture(T.linear), n))


def absorbed(n):
    import test_diagnose as T

    name = (
        "test_diagnose::test_with_the_model_mesh_s_error_absorbed_the_false_positive_rate_is_held"
    )
    return _named(name, T.absorbed_null_alarms(_fixture(T.linear), n))


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
