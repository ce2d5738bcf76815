"""Coverage, false-alarm and power of the statistics in ``calib.stats`` on cheap models.

Seeded simulations of the linearised calibration on phantom-like geometry
(:mod:`calib.stats.coverage`: points uniform by area on the upper half of a 150 mm
ellipsoid; 1 scan of 2000 points or 3 scans of 1000 on the same surface for coverage,
1500 / 3 x 1000 for the misfit test, 1000 / 3 x 700 for screening; a smooth
``dr / d ln c1`` vanishing at the rim), Gaussian noise with an exponential or Gaussian
kernel (length 2-20 mm, sigma 0.05-0.5 mm, nugget fraction 0-0.3), drawn exactly.
Each draw: ``theta_hat - theta = a' eps``, residual ``r = M eps``, noise model fitted to
``r`` (short-range variogram, 40 mm), then every method on the same draw.

Tables (``--table``):

- ``coverage``: empirical coverage of nominal 95 % intervals of theta: ``today`` (the
  formula of ``calib/fitting/uncertainty.py``: sd of r, 1/e length from 40 000 random
  pairs, ``n_eff = A / (pi l^2)``, z = 1.96, re-implemented here as it was when these
  tables were made; since then the Gauss-Newton interval, which only the landmarks
  objective and small surface samples keep, takes Student's t on ``n_eff - 1``), ``sandwich-z``
  (plug-in sandwich with the fitted model, z), ``series`` (the series estimator with its
  Imhof quantile, chosen kernel), ``series+alt`` (the widest over the plausible
  kernels: the default of :func:`calib.stats.intervals.parameter_intervals` when given
  ``NoiseFit.plausible``); with the median width relative to the oracle ``2 * 1.96 *
  sd(theta_hat)``. ``profile``: the likelihood profile of ``calib/fitting/profile.py``
  (``-2 dlogL = n_eff ln(S / S_min)``, today's ``n_eff``) read at chi2(1) 3.84; the tool
  prints its rows, not an interval, and in this linear model it is today's interval with
  ``exp(3.84 / n_eff) - 1`` for ``3.84 / n_eff``. The mesh check's GCI (added in
  quadrature by the tool) is zero here: there is no discretisation in a linear model.
- ``misfit``: false-alarm rate of :func:`calib.stats.scores.misfit_test` (band-F and
  chi2) on null residuals, and power against an added smooth ``p2`` pattern.
- ``session``: the misfit test as ``diagnose`` runs it, at the quietest scan's noise
  fit (:func:`calib.stats.noise.session_noise`, per-scan offsets projected out), against
  the true model and with each scan's own fit as further alternatives (review AV's
  proposal): false alarms on null residuals and power against a 30 mm bump at the apex.
- ``screen``: per-effect and family-wise (Holm) false-positive rates of
  :func:`calib.stats.scores.screen_effects` on null residuals, power for one effect,
  and the power at the size the screening reports as detectable.
- ``postures``: false-alarm rate of :func:`calib.stats.consistency.posture_consistency`
  (Cochran's Q of each scan's own estimate, the session's noise model) on null
  residuals of three scans, ``ln c1`` fitted on the first alone as ``calibrate`` does,
  and its power when the other two scans ask for a ``ln c1`` lower by ``shift``.
- ``variogram``: the fitted noise model (median length, sigma, kernel chosen) with the
  short-range cutoff, all lags, and a quadratic detrend, without and with a misfit.
- ``effective``: the local effective-sample approximation against exact whitening.

Every proportion is printed with its binomial standard error ``sqrt(p (1 - p) / N)``.
Sigma only scales the problem (every method is scale-equivariant), so cells differing
only in sigma differ by their random draws.

    python benchmarks/bench_coverage.py --table coverage --draws 1000      # ~40 min, 1 core
    python benchmarks/bench_coverage.py --table all --draws 1000 --workers 2
    python benchmarks/bench_coverage.py --quick                            # 2 cells, 200 draws
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
from _provenance import print_header

from calib.stats.consistency import posture_consistency
from calib.stats.coverage import (
    NoiseSampler,
    misfit_pattern,
    phantom_sample,
    sag_sensitivity,
)
from calib.stats.intervals import series_design, series_statistic
from calib.stats.noise import (
    NoiseModel,
    apply_covariance,
    empirical_variogram,
    fit_variogram,
    local_counts,
    whitener,
)
from calib.stats.quadform import ratio_critical_value
from calib.stats.scores import misfit_design, misfit_test, screen_effects

HALF_ELLIPSOID_AREA_MM2 = 30736.6  # upper half of the (75, 75, 60) mm spheroid
POWER_DRAWS = 300  # draws with a planted pattern or effect (power needs no 1000)


def _progress(table: str, cell, t0: float) -> None:
    print(f"  [{table}] {cell.label}: {time.perf_counter() - t0:.0f} s", file=sys.stderr,
          flush=True)  # fmt: skip


@dataclass(frozen=True)
class Cell:
    kernel: str
    length_mm: float
    sigma_mm: float
    nugget: float
    n_per_scan: int
    n_scans: int

    @property
    def label(self) -> str:
        return (f"{self.kernel[:5]:5s} l={self.length_mm:4.1f} s={self.sigma_mm:.2f} "
                f"f={self.nugget:.1f} {self.n_scans}x{self.n_per_scan}")  # fmt: skip

    def model(self) -> NoiseModel:
        return NoiseModel(self.kernel, self.sigma_mm, self.nugget, self.length_mm)


def coverage_cells(quick: bool) -> list[Cell]:
    if quick:
        return [
            Cell("exponential", 10.0, 0.3, 0.0, 1500, 1),
            Cell("gaussian", 5.0, 0.3, 0.3, 1500, 1),
        ]
    cells = []
    for kernel in ("exponential", "gaussian"):
        for length in (2.0, 5.0, 10.0, 20.0):
            cells.append(Cell(kernel, length, 0.05, 0.0, 2000, 1))
            cells.append(Cell(kernel, length, 0.5, 0.3, 2000, 1))
        for length in (5.0, 20.0):
            cells.append(Cell(kernel, length, 0.2, 0.1, 1000, 3))
    return cells


def binom(hits: np.ndarray) -> str:
    p = float(np.mean(hits))
    return f"{100 * p:5.1f} ({100 * np.sqrt(p * (1 - p) / len(hits)):3.1f})"


# ------------------------------------------------------------------- today's formula


def today_half_width(points, r, J, area_mm2, seed=0):
    """Half-widths of calib/fitting's Gauss-Newton interval and profile (re-implemented).

    Returns ``(gauss_newton, profile)`` in theta: ``1.96 sd / |J| sqrt(n / n_eff)``
    (``calib/fitting/uncertainty.py``) and where ``n_eff ln(S / S_min)`` reaches 3.84 with
    ``S = S_min + d^2 J'J`` (``calib/fitting/profile.py``'s profile of a linear model).
    """
    n = len(r)
    sd = float(np.sqrt(np.sum(r**2) / (n - 1)))
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, 40000), rng.integers(0, n, 40000)
    d = np.linalg.norm(points[i] - points[j], axis=1)
    z = (r - r.mean()) / r.std()
    prod = z[i] * z[j]
    edges = np.linspace(0.0, np.percentile(d, 90), 31)
    idx = np.digitize(d, edges) - 1
    ell = float(edges[-1])
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() >= 30 and prod[sel].mean() < np.exp(-1.0):
            ell = float(0.5 * (edges[b] + edges[b + 1]))
            break
    n_eff = float(np.clip(area_mm2 / (np.pi * ell**2), 2, n)) if ell > 0 else float(n)
    info = float(np.sum(J**2))
    se = sd / np.sqrt(info) * np.sqrt(n / n_eff)
    profile = np.sqrt(float(np.sum(r**2)) / info * np.expm1(3.841458820694124 / n_eff))
    return 1.959963984540054 * se, float(profile)


# ------------------------------------------------------------------------- coverage


def run_coverage(cell: Cell, draws: int, seed: int) -> dict:
    sample = phantom_sample(cell.n_per_scan, cell.n_scans, seed=seed)
    J = sag_sensitivity(sample)
    sampler = NoiseSampler.of(sample, cell.model())
    design = series_design(sample, J)
    a = design.influence
    rng = np.random.default_rng(seed + 1)
    area = HALF_ELLIPSOID_AREA_MM2 * cell.n_scans
    out = {k: [] for k in ("today", "profile", "sandwich-z", "series", "series+alt")}
    widths = {k: [] for k in out}
    err, dof, kern = [], [], []
    t0 = time.perf_counter()
    for _ in range(draws):
        eps = sampler.draw(rng)[:, 0]
        e = float(a @ eps)  # theta_hat - theta
        r = eps - J * float(J @ eps) / float(J @ J)
        fit = fit_variogram(empirical_variogram(sample, r))
        gn, prof = today_half_width(sample.points_mm, r, J, area)
        half = {"today": gn, "profile": prof}
        best = None
        for k, model in enumerate(fit.plausible):
            st = series_statistic(design, r, model)
            hw = ratio_critical_value(st.omega, st.weights) * st.standard_error
            if k == 0:
                half["sandwich-z"] = 1.959963984540054 * st.plugin_standard_error
                half["series"] = hw
                dof.append(st.dof)
            best = hw if best is None else max(best, hw)
        half["series+alt"] = best
        for k, h in half.items():
            out[k].append(abs(e) <= h)
            widths[k].append(h)
        err.append(e)
        kern.append(fit.best.kernel)
    oracle = 1.959963984540054 * float(np.sqrt(a @ apply_covariance(sample, cell.model(), a)))
    _progress("coverage", cell, t0)
    return {
        "cell": cell,
        "hits": {k: np.array(v) for k, v in out.items()},
        "width": {k: float(np.median(v)) / oracle for k, v in widths.items()},
        "sd_ratio": float(np.std(err)) * 1.959963984540054 / oracle,
        "dof": float(np.median(dof)),
        "kernel_ok": float(np.mean([k == cell.kernel for k in kern])),
        "seconds": time.perf_counter() - t0,
        "draws": draws,
    }


def print_coverage(results: list[dict]) -> None:
    methods = ("today", "profile", "sandwich-z", "series", "series+alt")
    print("\nCoverage of nominal 95 % intervals of theta, % (binomial se); width = median "
          "interval / oracle 2 x 1.96 sd(theta_hat)")  # fmt: skip
    head = " | ".join(f"{m:>12s}" for m in methods)
    print(f"| {'cell':36s} | draws | {head} | width today/series+alt | dof | kernel ok |")
    for res in results:
        cov = " | ".join(f"{binom(res['hits'][m]):>12s}" for m in methods)
        w = res["width"]
        print(f"| {res['cell'].label:36s} | {res['draws']:5d} | {cov} | "
              f"{w['today']:.2f} / {w['series+alt']:.2f} | {res['dof']:4.1f} | "
              f"{100 * res['kernel_ok']:3.0f} % |")  # fmt: skip


# --------------------------------------------------------------------------- misfit


def misfit_cells(quick: bool) -> list[Cell]:
    if quick:
        return [Cell("exponential", 10.0, 0.3, 0.0, 1500, 1)]
    cells = []
    for kernel in ("exponential", "gaussian"):
        for length in (2.0, 5.0, 10.0, 20.0):
            cells.append(Cell(kernel, length, 0.3, 0.0 if length > 5 else 0.3, 1500, 1))
        cells.append(Cell(kernel, 10.0, 0.2, 0.1, 1000, 3))
    return cells


AMPLITUDES = (0.0, 0.1, 0.2, 0.4, 0.8)  # misfit RMS in units of sigma


def run_misfit(cell: Cell, draws: int, seed: int, power: bool) -> dict:
    sample = phantom_sample(cell.n_per_scan, cell.n_scans, seed=seed)
    J = sag_sensitivity(sample)
    sampler = NoiseSampler.of(sample, cell.model())
    design = misfit_design(sample, J)
    pattern = misfit_pattern(sample, kind="p2") * cell.sigma_mm
    rng = np.random.default_rng(seed + 2)
    amps = AMPLITUDES if power else (0.0,)
    p = {(m, amp): [] for m in ("band-F", "chi2") for amp in amps}
    t0 = time.perf_counter()
    for k in range(draws):
        eps = sampler.draw(rng)[:, 0]
        for amp in amps if k < POWER_DRAWS else (0.0,):
            x = eps + amp * pattern
            r = x - J * float(J @ x) / float(J @ J)
            fit = fit_variogram(empirical_variogram(sample, r))
            res = misfit_test(r, J, sample, fit.best, alternatives=fit.plausible[1:],
                              design=design)  # fmt: skip
            p[("band-F", amp)].append(res.p_value)
            p[("chi2", amp)].append(res.chi2_p_value)
    _progress("misfit", cell, t0)
    return {"cell": cell, "p": {k: np.array(v) for k, v in p.items()}, "draws": draws,
            "seconds": time.perf_counter() - t0, "amps": amps}  # fmt: skip


def print_misfit(results: list[dict]) -> None:
    print("\nMisfit test: rejection rate % (binomial se) on null residuals (correlated noise only)")
    print(f"| {'cell':36s} | draws | band-F a=0.05 | band-F a=0.01 | chi2 a=0.05 | chi2 a=0.01 |")
    for res in results:
        row = []
        for m in ("band-F", "chi2"):
            for alpha in (0.05, 0.01):
                row.append(f"{binom(res['p'][(m, 0.0)] < alpha):>11s}")
        print(f"| {res['cell'].label:36s} | {res['draws']:5d} | " + " | ".join(row) + " |")
    pw = [r for r in results if len(r["amps"]) > 1]
    if not pw:
        return
    amps = pw[0]["amps"][1:]
    print(
        "\nMisfit test: power % at alpha = 0.01 against an added p2 pattern of RMS amplitude "
        f"x sigma (after the fit absorbs what it can), {len(pw[0]['p'][('band-F', amps[0])])} "
        "draws per amplitude"
    )
    print(f"| {'cell':36s} | method | " + " | ".join(f"{a:>10.2f}" for a in amps) + " |")
    for res in pw:
        for m in ("band-F", "chi2"):
            row = " | ".join(f"{binom(res['p'][(m, a)] < 0.01):>10s}" for a in amps)
            print(f"| {res['cell'].label:36s} | {m:6s} | {row} |")


# ---------------------------------------------------------- misfit with the session fit


def session_cells(quick: bool) -> list[Cell]:
    if quick:
        return [Cell("exponential", 12.0, 0.1, 0.2, 500, 2)]
    return [
        Cell("exponential", 12.0, 0.1, 0.2, 500, 2),
        Cell("exponential", 10.0, 0.2, 0.1, 1000, 3),
        Cell("exponential", 5.0, 0.2, 0.1, 1000, 3),
    ]


SESSION_VARIANTS = ("true model", "session fit", "+ each scan's fit")


def run_session(cell: Cell, draws: int, seed: int) -> dict:
    """``diagnose``'s misfit test (band F at its noise model, the quietest scan's fit of
    the per-scan centred residual, ``calib.stats.noise.session_noise``) on null draws and
    against a 30 mm bump at the apex in every scan, beside the true model and the
    session fit with each scan's own fit as further alternatives (review AV)."""
    from calib.discrepancy.screen import offset_columns
    from calib.stats.noise import session_noise

    sample = phantom_sample(cell.n_per_scan, cell.n_scans, seed=seed)
    c1 = sag_sensitivity(sample)
    offsets = offset_columns(sample)  # as diagnose projects them out
    J = np.column_stack([c1, offsets])
    design = misfit_design(sample, J)
    sampler = NoiseSampler.of(sample, cell.model())
    bump = misfit_pattern(sample, kind="bump") * cell.sigma_mm
    rng = np.random.default_rng(seed + 5)
    amps = (0.0, 2.0, 4.0, 8.0)  # the bump's RMS in units of sigma
    p = {(v, a): [] for v in SESSION_VARIANTS for a in amps}
    t0 = time.perf_counter()
    for k in range(draws):
        eps = sampler.draw(rng)[:, 0]
        for amp in amps if k < POWER_DRAWS else (0.0,):
            x = eps + amp * bump
            r = x - c1 * float(c1 @ x) / float(c1 @ c1)
            r_c = r - offsets @ np.linalg.lstsq(offsets, r, rcond=None)[0]
            fit = session_noise(sample, r_c, max_lag_mm=40.0)
            others = [m for s, m in fit.scan_fits.items() if s != fit.reference_scan]
            each = (*fit.alternatives, dict(fit.scan_fits), *others)
            for variant, noise, alt in (
                ("true model", cell.model(), ()),
                ("session fit", fit.best_arg, fit.alternatives),  # diagnose's
                ("+ each scan's fit", fit.best_arg, each),
            ):
                res = misfit_test(r, J, sample, noise, alternatives=alt, design=design)
                p[(variant, amp)].append(res.p_value)
    _progress("session", cell, t0)
    return {"cell": cell, "p": {k: np.array(v) for k, v in p.items()}, "amps": amps,
            "seconds": time.perf_counter() - t0}  # fmt: skip


def print_session(results: list[dict]) -> None:
    print(
        "\nMisfit test with diagnose's session noise fit: rejection rate % (binomial se), "
        "band F; null draws, then power at alpha = 0.01 against a 30 mm bump at the apex "
        "of RMS 2, 4 and 8 sigma in every scan"
    )
    print(f"| {'cell':36s} | {'noise model':18s} | a=0.05 null | a=0.01 null | "
          "bump 2 sigma | bump 4 sigma | bump 8 sigma |")  # fmt: skip
    for res in results:
        for v in SESSION_VARIANTS:
            row = [binom(res["p"][(v, 0.0)] < a) for a in (0.05, 0.01)]
            row += [binom(res["p"][(v, a)] < 0.01) for a in res["amps"][1:]]
            print(f"| {res['cell'].label:36s} | {v:18s} | " + " | ".join(f"{c:>11s}" for c in row)
                  + " |")  # fmt: skip


# ------------------------------------------------------------------------ screening


def screen_cells(quick: bool) -> list[Cell]:
    if quick:
        return [Cell("exponential", 10.0, 0.3, 0.0, 1000, 1)]
    return [
        Cell("exponential", 5.0, 0.3, 0.3, 1000, 1),
        Cell("exponential", 20.0, 0.3, 0.0, 1000, 1),
        Cell("gaussian", 10.0, 0.3, 0.0, 1000, 1),
        Cell("exponential", 10.0, 0.2, 0.1, 700, 3),
    ]


EFFECTS = ("p2", "tilt", "bump", "sag-tilt")


def effect_fields(sample, J) -> np.ndarray:
    """Smooth candidate sensitivity fields (mm per unit); ``sag-tilt`` ~ mostly J."""
    cols = [misfit_pattern(sample, kind=k) for k in ("p2", "tilt", "bump")]
    x, _, _ = sample.points_mm.T
    cols.append(J * (1.0 + 0.05 * x / 75.0))  # nearly absorbed by c1: not identifiable
    return np.column_stack(cols)


def run_screen(cell: Cell, draws: int, seed: int) -> dict:
    sample = phantom_sample(cell.n_per_scan, cell.n_scans, seed=seed)
    J = sag_sensitivity(sample)
    S = effect_fields(sample, J)
    sampler = NoiseSampler.of(sample, cell.model())
    rng = np.random.default_rng(seed + 3)
    p, ident, alt, cond, sizes = [], [], [], [], []
    t0 = time.perf_counter()
    signal = 0.3 * cell.sigma_mm * S[:, 0]  # an effect of 0.3 sigma RMS (p2)
    Jc = np.column_stack([J, S[:, 0]])  # forward step: p2 named and fitted with c1
    cosine = None
    for k in range(draws):
        eps = sampler.draw(rng)[:, 0]
        for x, store in ((eps, p), (eps + signal, alt))[: 2 if k < POWER_DRAWS else 1]:
            r = x - J * float(J @ x) / float(J @ J)
            fit = fit_variogram(empirical_variogram(sample, r))
            res = screen_effects(r, J, S, EFFECTS, sample, fit.best,
                                 alternatives=fit.plausible[1:])  # fmt: skip
            store.append([e.p_value for e in res.effects] + [e.significant for e in res.effects])
            if store is p:
                ident.append([e.identifiable for e in res.effects])
                sizes.append(res.effects[0].detectable)
                cosine = res.cosine
                continue
            rc = x - Jc @ np.linalg.lstsq(Jc, x, rcond=None)[0]
            fit = fit_variogram(empirical_variogram(sample, rc))
            res = screen_effects(rc, Jc, S[:, 1:3], EFFECTS[1:3], sample, fit.best,
                                 alternatives=fit.plausible[1:])  # fmt: skip
            cond.append(any(e.significant for e in res.effects))
    # p2 planted at the median of the size the null draws report (EffectScore.detectable:
    # 80 % power after Holm, nominally)
    size = float(np.median(sizes))
    found = []
    for _ in range(POWER_DRAWS):
        x = sampler.draw(rng)[:, 0] + size * S[:, 0]
        r = x - J * float(J @ x) / float(J @ J)
        fit = fit_variogram(empirical_variogram(sample, r))
        res = screen_effects(r, J, S, EFFECTS, sample, fit.best, alternatives=fit.plausible[1:])
        found.append(res.effects[0].significant)
    _progress("screen", cell, t0)
    return {"cell": cell, "p": np.array(p, dtype=float), "alt": np.array(alt, dtype=float),
            "ident": np.array(ident), "cond": np.array(cond), "cosine": cosine,
            "size": size, "size_spread": float(np.std(sizes) / size), "found": np.array(found),
            "draws": draws, "seconds": time.perf_counter() - t0}  # fmt: skip


def print_screen(results: list[dict]) -> None:
    print("\nEffect screening on null residuals: rejection % (binomial se) per effect at "
          "alpha = 0.05 (unadjusted), and family-wise (Holm, alpha = 0.05)")  # fmt: skip
    names = " | ".join(f"{n:>11s}" for n in EFFECTS[:3])
    print(f"| {'cell':36s} | draws | {names} | family-wise | {EFFECTS[3]} identifiable |")
    for res in results:
        q = res["p"]
        row = " | ".join(f"{binom(q[:, k] < 0.05):>11s}" for k in range(3))
        fw = q[:, len(EFFECTS) :].max(axis=1) > 0
        print(f"| {res['cell'].label:36s} | {res['draws']:5d} | {row} | {binom(fw):>11s} "
              f"| {100 * res['ident'][:, 3].mean():5.1f} % |")  # fmt: skip
    print(
        f"\nPower: an effect of 0.3 sigma RMS along p2 added ({len(results[0]['alt'])} draws): "
        "% of draws "
        "where each effect is significant after Holm (marginal score tests: an effect whose "
        "signature resembles p2's responds too), and where tilt or bump still is once p2 is "
        "fitted with c1 (the forward step of the diagnosis); cos = cosine of the projected "
        "whitened signatures with p2"
    )
    for res in results:
        q = res["alt"]
        k = len(EFFECTS)
        row = " | ".join(f"{n} {binom(q[:, k + i] > 0)}" for i, n in enumerate(EFFECTS[:3]))
        cos = res["cosine"][0, 1:3]
        print(f"| {res['cell'].label:36s} | {row} | after p2: {binom(res['cond'])} | "
              f"cos tilt {cos[0]:+.2f}, bump {cos[1]:+.2f} |")  # fmt: skip
    print(
        "\nThe reported detectable size (EffectScore.detectable, 80 % power after Holm "
        "nominally): p2's median over the null draws (its spread across draws, sd / median), "
        f"and the % of {POWER_DRAWS} draws with p2 planted at that size where p2 is significant"
    )
    for res in results:
        size = f"size {res['size']:.4g} ({100 * res['size_spread']:.0f} %)"
        print(f"| {res['cell'].label:36s} | {size} | {binom(res['found'])} |")


# ------------------------------------------------------------------------ variogram


def run_variogram(draws: int, seed: int) -> None:
    print("\nNoise model fitted to residuals: median length / true, sigma / true (10-90 %), "
          "kernel chosen correctly; misfit = p2 pattern of 0.4 sigma RMS")  # fmt: skip
    print(f"| {'cell':36s} | misfit | {'estimate':22s} | length ratio | sigma ratio | kernel ok |")
    for kernel, length in (("exponential", 5.0), ("exponential", 20.0), ("gaussian", 10.0)):
        cell = Cell(kernel, length, 0.3, 0.0, 2000, 1)
        sample = phantom_sample(cell.n_per_scan, 1, seed=seed)
        J = sag_sensitivity(sample)
        sampler = NoiseSampler.of(sample, cell.model())
        pattern = misfit_pattern(sample) * cell.sigma_mm
        for amp in (0.0, 0.4):
            rng = np.random.default_rng(seed + 4)
            est = {"short range (40 mm)": dict(max_lag_mm=40.0),
                   "all lags (150 mm)": dict(max_lag_mm=150.0),
                   "quadratic detrend, 40": dict(max_lag_mm=40.0, detrend="quadratic")}  # fmt: skip
            rows = {k: [] for k in est}
            for _ in range(draws):
                x = sampler.draw(rng)[:, 0] + amp * pattern
                r = x - J * float(J @ x) / float(J @ J)
                for k, kw in est.items():
                    m = fit_variogram(empirical_variogram(sample, r, **kw)).best
                    rows[k].append((m.length_mm / length, m.sigma_mm / cell.sigma_mm,
                                    m.kernel == kernel))  # fmt: skip
            for k, v in rows.items():
                v = np.array(v, dtype=float)
                lq = np.percentile(v[:, 0], [10, 50, 90])
                sq = np.percentile(v[:, 1], [10, 50, 90])
                print(f"| {cell.label:36s} | {amp:6.1f} | {k:22s} | {lq[1]:.2f} ({lq[0]:.2f}-"
                      f"{lq[2]:.2f}) | {sq[1]:.2f} ({sq[0]:.2f}-{sq[2]:.2f}) | "
                      f"{100 * v[:, 2].mean():3.0f} % |")  # fmt: skip


# ------------------------------------------------------------------------ effective


def run_effective(seed: int) -> None:
    import calib.stats.scores as scores_mod

    print(
        "\nLocal effective-sample approximation x' Sigma^-1 x ~ sum x^2 / (sigma^2 m) vs exact "
        "whitening (1 scan, 2000 points): relative error of the quadratic form per field, and "
        "the largest error of the retained fractions and cosines of (p2, tilt, bump) after J"
    )
    sample = phantom_sample(2000, 1, seed=seed)
    J = sag_sensitivity(sample)
    fields = {
        "J (sag)": J,
        "p2": misfit_pattern(sample),
        "tilt": misfit_pattern(sample, kind="tilt"),
        "bump 30 mm": misfit_pattern(sample, kind="bump"),
    }
    S = np.column_stack(list(fields.values())[1:])
    head = " | ".join(f"{k:>10s}" for k in fields)
    print(f"| {'kernel':11s} | l mm | nugget | {head} | retained | cosine | n_eff (mean) |")
    for kernel in ("exponential", "gaussian"):
        for length in (2.0, 5.0, 10.0, 20.0):
            for nug in (0.0, 0.3):
                model = NoiseModel(kernel, 0.3, nug, length)
                w = whitener(sample, model)
                m = local_counts(sample, model)
                errs = []
                for x in fields.values():
                    exact = float(np.sum(w.apply(x) ** 2))
                    approx = float(np.sum(x * x / (model.sigma_mm**2 * m)))
                    errs.append(approx / exact - 1.0)
                ret, cos, _ = scores_mod.signature_geometry(sample, J, S, model)
                limit = scores_mod.MAX_DENSE_BLOCK
                scores_mod.MAX_DENSE_BLOCK = 10
                try:
                    ret2, cos2, _ = scores_mod.signature_geometry(sample, J, S, model)
                finally:
                    scores_mod.MAX_DENSE_BLOCK = limit
                n_eff = sample.n**2 / float(np.sum(m))
                cells = " | ".join(f"{100 * e:+9.1f}%" for e in errs)
                print(
                    f"| {kernel:11s} | {length:4.0f} | {nug:6.1f} | {cells} | "
                    f"{np.max(np.abs(ret2 - ret)):8.3f} | {np.max(np.abs(cos2 - cos)):6.3f} | "
                    f"{n_eff:12.0f} |"
                )


# ------------------------------------------------------------------ posture consistency


def posture_cells(quick: bool) -> list[Cell]:
    if quick:
        return [Cell("exponential", 5.0, 0.15, 0.2, 600, 3)]
    return [
        Cell(kernel, length, 0.15, 0.2, 600, 3)
        for kernel in ("exponential", "gaussian")
        for length in (2.0, 5.0, 10.0)
    ]


SHIFTS = (0.0, 0.02, 0.04, 0.08)  # the tilted scans' ln c1 below the lateral one's
POSTURE_GAIN = (4.0, 1.0, 2.0)  # |dr/d ln c1| of a lateral and two tilted scans, relative


def run_postures(cell: Cell, draws: int, seed: int) -> dict:
    sample = phantom_sample(cell.n_per_scan, cell.n_scans, seed=seed)
    J = sag_sensitivity(sample, posture_deg=(0.0, 60.0, 150.0))
    J = J * np.repeat(POSTURE_GAIN, cell.n_per_scan)
    sampler = NoiseSampler.of(sample, cell.model())
    b0 = sample.blocks[0]
    rng = np.random.default_rng(seed + 3)
    p = {shift: [] for shift in SHIFTS}
    t0 = time.perf_counter()
    for k in range(draws):
        eps = sampler.draw(rng)[:, 0]
        for shift in SHIFTS if k < POWER_DRAWS else (0.0,):
            x = eps.copy()
            for idx in sample.blocks[1:]:
                x[idx] += J[idx] * shift  # the scan alone asks for ln c1 lower by shift
            r = x - J * float(J[b0] @ x[b0]) / float(J[b0] @ J[b0])  # fitted on scan 0
            p[shift].append(posture_consistency(0.0, r, J, sample).p_value)
    _progress("postures", cell, t0)
    return {"cell": cell, "p": {k: np.array(v) for k, v in p.items()}, "draws": draws}


def print_postures(results: list[dict]) -> None:
    print(
        "\nPosture consistency: rejection rate % (binomial se) on null residuals of 3 scans "
        "(ln c1 fitted on the first)"
    )
    print(f"| {'cell':36s} | draws | a=0.01 | a=0.04 | a=0.05 |")
    for res in results:
        row = " | ".join(binom(res["p"][0.0] < a) for a in (0.01, 0.04, 0.05))
        print(f"| {res['cell'].label:36s} | {res['draws']:5d} | {row} |")
    n = len(results[0]["p"][SHIFTS[1]])
    print(
        f"\nPosture consistency: power % at alpha = 0.04 when two scans ask for ln c1 lower "
        f"by shift, {n} draws per shift"
    )
    print(f"| {'cell':36s} | " + " | ".join(f"{s:>10.2f}" for s in SHIFTS[1:]) + " |")
    for res in results:
        row = " | ".join(f"{binom(res['p'][s] < 0.04):>10s}" for s in SHIFTS[1:])
        print(f"| {res['cell'].label:36s} | {row} |")


# ----------------------------------------------------------------------------- main


def _map(fn, jobs, workers):
    if workers <= 1:
        return [fn(*j) for j in jobs]
    from multiprocessing import Pool

    with Pool(workers) as pool:  # one cell per task: cells differ in cost by 3x
        return pool.starmap(fn, jobs, chunksize=1)


#: the tables, in the order ``--table all`` prints them
TABLES = ("coverage", "misfit", "session", "screen", "postures", "variogram", "effective")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--table",
        default="coverage",
        choices=[*TABLES, "all"],
    )
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="2 cells, 200 draws")  # fmt: skip
    args = ap.parse_args()
    draws = 200 if args.quick else args.draws
    tables = list(TABLES) if args.table == "all" else [args.table]
    print_header(("numpy", "scipy"))
    t0 = time.perf_counter()
    print(f"bench_coverage: tables {tables}, {draws} draws per cell, seed {args.seed}, "
          f"numpy {np.__version__}")  # fmt: skip
    if "coverage" in tables:
        cells = coverage_cells(args.quick)
        print_coverage(_map(run_coverage, [(c, draws, args.seed) for c in cells], args.workers))
    if "misfit" in tables:
        cells = misfit_cells(args.quick)
        jobs = [(c, draws, args.seed, c.n_scans == 1 and c.length_mm in (2.0, 5.0, 10.0, 20.0)
                 and c.kernel == "exponential") for c in cells]  # fmt: skip
        print_misfit(_map(run_misfit, jobs, args.workers))
    if "session" in tables:
        cells = session_cells(args.quick)
        print_session(_map(run_session, [(c, draws, args.seed) for c in cells], args.workers))
    if "screen" in tables:
        cells = screen_cells(args.quick)
        print_screen(_map(run_screen, [(c, draws, args.seed) for c in cells], args.workers))
    if "postures" in tables:
        cells = posture_cells(args.quick)
        print_postures(_map(run_postures, [(c, draws, args.seed) for c in cells], args.workers))
    if "variogram" in tables:
        run_variogram(min(draws, 200), args.seed)
    if "effective" in tables:
        run_effective(args.seed)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; command: python benchmarks/bench_coverage.py "
          f"--table {args.table} --draws {draws} --seed {args.seed}"
          + (" --quick" if args.quick else ""))  # fmt: skip


if __name__ == "__main__":
    main()
