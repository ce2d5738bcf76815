"""The noise model of calib.stats: kernels, variogram, kernel fit, covariances, whitening.

Closed forms (kernel values, correlation areas), two code paths agreeing (binned vs
brute-force variogram, chunked vs dense covariance, row sums vs the dense matrix), and
recovery of a hidden truth (a fit to an exact model variogram returns the model; a fit
to one seeded noise draw lands within the spread measured by
``benchmarks/bench_coverage.py --table variogram``).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

import calib.stats.noise as noise_mod
import calib.stats.sample as sample_mod
from calib.stats.coverage import NoiseSampler, misfit_pattern, phantom_sample, sag_sensitivity
from calib.stats.kernels import (
    KERNELS,
    UnknownKernelError,
    correlation,
    correlation_area_mm2,
    one_over_e_distance_mm,
    truncation_distance_mm,
)
from calib.stats.noise import (
    NoiseModel,
    NoiseModelError,
    Variogram,
    apply_covariance,
    covariance_matrix,
    effective_sample_count,
    empirical_variogram,
    estimate_noise,
    fit_variogram,
    local_counts,
    whitener,
)
from calib.stats.sample import SampleError, SurfaceSample


@pytest.fixture(scope="module")
def small():
    return phantom_sample(600, 2, seed=3)


# ----------------------------------------------------------------------------- kernels


def test_kernel_values_closed_form():
    h = np.array([0.0, 2.0])
    assert correlation("exponential", h, 2.0) == pytest.approx([1.0, np.exp(-1.0)], rel=1e-14)
    assert correlation("gaussian", h, 2.0) == pytest.approx([1.0, np.exp(-0.5)], rel=1e-14)
    s3 = np.sqrt(3.0)
    assert correlation("matern32", h, 2.0) == pytest.approx(
        [1.0, (1 + s3) * np.exp(-s3)], rel=1e-14
    )
    assert correlation("gaussian", h, 0.0).tolist() == [1.0, 0.0]  # white noise


@pytest.mark.parametrize("kernel", KERNELS)
def test_kernel_area_one_over_e_and_truncation(kernel):
    ell = 3.7
    area, _ = quad(lambda h: 2 * np.pi * h * correlation(kernel, h, ell), 0, np.inf)
    assert area == pytest.approx(correlation_area_mm2(kernel, ell), rel=1e-8)  # quad accuracy
    assert correlation(kernel, one_over_e_distance_mm(kernel, ell), ell) == pytest.approx(
        np.exp(-1.0), rel=1e-9
    )
    assert correlation(kernel, truncation_distance_mm(kernel, ell), ell) == pytest.approx(
        1e-4, rel=1e-6
    )


def test_unknown_kernel_is_named():
    with pytest.raises(UnknownKernelError, match="'cauchy'"):
        correlation("cauchy", np.ones(2), 1.0)


# ------------------------------------------------------------------------------ sample


def test_sample_rejects_bad_inputs():
    with pytest.raises(SampleError, match=r"shape \(n, 3\)"):
        SurfaceSample(np.zeros((4, 2)))
    with pytest.raises(SampleError, match="scan must have shape"):
        SurfaceSample(np.zeros((4, 3)), np.zeros(3, int))
    with pytest.raises(SampleError, match="integers"):
        SurfaceSample(np.zeros((4, 3)), np.zeros(4))
    with pytest.raises(SampleError, match="non-finite"):
        SurfaceSample(np.full((4, 3), np.nan))
    s = SurfaceSample(np.random.default_rng(0).normal(size=(5, 3)))
    with pytest.raises(SampleError, match=r"residual_mm must have shape \(5,\)"):
        empirical_variogram(s, np.zeros(4))


def test_pairs_never_join_scans(small):
    # two scans on the same surface, each residual constant: a cross-scan pair would
    # give a non-zero semivariance
    pairs = small.pairs(40.0)
    assert np.all(small.scan[pairs.i] == small.scan[pairs.j])
    assert pairs.distance_mm.max() <= 40.0
    r = np.where(small.scan == 0, 1.0, -1.0)
    with pytest.raises(NoiseModelError, match="variogram is zero"):
        fit_variogram(empirical_variogram(small, r))


def test_pairs_are_thinned_reproducibly(small):
    a = small.pairs(40.0, max_pairs=5000, seed=4)
    b = SurfaceSample(small.points_mm, small.scan).pairs(40.0, max_pairs=5000, seed=4)
    assert a.thinned and len(a.i) == 5000
    assert np.array_equal(a.i, b.i) and np.array_equal(a.j, b.j)


# --------------------------------------------------------------------------- variogram


def test_variogram_matches_brute_force(small):
    rng = np.random.default_rng(1)
    r = rng.normal(size=small.n)
    vg = empirical_variogram(small, r, max_lag_mm=30.0, n_bins=10, min_pairs=1)
    # brute force: every within-scan pair, Matheron's estimator per bin
    gam, cnt = np.zeros(10), np.zeros(10)
    for idx in small.blocks:
        p = small.points_mm[idx]
        d = np.linalg.norm(p[:, None] - p[None], axis=2)
        iu = np.triu_indices(len(idx), 1)
        dd = d[iu]
        sq = 0.5 * (r[idx][iu[0]] - r[idx][iu[1]]) ** 2
        ok = dd < 30.0
        b = np.minimum((dd[ok] / 3.0).astype(int), 9)
        np.add.at(gam, b, sq[ok])
        np.add.at(cnt, b, 1)
    keep = cnt > 0
    assert vg.n_pairs.tolist() == cnt[keep].astype(int).tolist()
    assert vg.gamma_mm2 == pytest.approx(gam[keep] / cnt[keep], rel=1e-12)


def _exact_variogram(model: NoiseModel, max_lag=40.0, bins=20) -> Variogram:
    lag = (np.arange(bins) + 0.5) * max_lag / bins
    n = np.full(bins, 5000, dtype=np.int64)
    return Variogram(lag, model.semivariance_mm2(lag), n, model.sigma_mm**2, max_lag, "none",
                     False, 0)  # fmt: skip


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("ell,nugget", [(3.0, 0.0), (8.0, 0.2), (15.0, 0.5)])
def test_fit_recovers_exact_model(kernel, ell, nugget):
    truth = NoiseModel(kernel, 0.3, nugget, ell)
    fit = fit_variogram(_exact_variogram(truth))
    m = fit.best
    assert m.kernel == kernel
    # the exact model is in the family: the profile fit reaches it to the scalar
    # search's tolerance (xatol 1e-4 in log l)
    assert m.length_mm == pytest.approx(ell, rel=1e-3)
    assert m.sigma_mm == pytest.approx(0.3, rel=1e-4)
    assert m.nugget_fraction == pytest.approx(nugget, abs=1e-4)
    # its misfit criterion vanishes but for that tolerance: measured 2e-11 to 1.8e-6, where
    # the other kernels' are 14 or more (review CF-17: the bar had no source)
    assert m.criterion < 1e-5
    assert fit.plausible[0] is m and len(fit.candidates) == 3


def test_fit_white_noise_is_pure_nugget():
    white = _exact_variogram(NoiseModel("exponential", 0.2, 1.0, 0.0))
    m = fit_variogram(white).best
    assert m.nugget_fraction == 1.0 and m.length_mm == 0.0
    assert m.sigma_mm == pytest.approx(0.2, rel=1e-12)


def test_fit_recovers_hidden_model_from_one_draw():
    # exponential, 6 mm, nugget 0.2, 2000 points. The bench's variogram table gives the
    # 10-90 % spread of the fitted length at about +-17 % (5 mm) and of sigma +-4 %; a
    # single seeded draw is asserted within twice that.
    sample = phantom_sample(2000, 1, seed=5)
    truth = NoiseModel("exponential", 0.3, 0.2, 6.0)
    r = NoiseSampler.of(sample, truth).draw(np.random.default_rng(2))[:, 0]
    m = estimate_noise(sample, r).best
    assert m.length_mm == pytest.approx(6.0, rel=0.35)
    assert m.sigma_mm == pytest.approx(0.3, rel=0.08)
    assert m.nugget_fraction == pytest.approx(0.2, abs=0.15)
    # review CF-17: one draw's nugget bar passed a fit returning 0.1 or 0.3 whatever the
    # data. Over 40 other seeded draws (1 s) the medians: nugget 0.214 (10-90 %: 0.16-0.35,
    # so the median's sd is ~0.015), length 5.9 mm, sigma 0.299 mm; each held within
    # about 3 of its median's sd of the truth
    sampler = NoiseSampler.of(sample, truth)
    fits = [estimate_noise(sample, sampler.draw(np.random.default_rng(100 + k))[:, 0]).best
            for k in range(40)]  # fmt: skip
    assert np.median([f.nugget_fraction for f in fits]) == pytest.approx(0.2, abs=0.05)
    assert np.median([f.length_mm for f in fits]) == pytest.approx(6.0, rel=0.1)
    assert np.median([f.sigma_mm for f in fits]) == pytest.approx(0.3, rel=0.02)
    assert not m.length_at_bound


def test_per_scan_scope_gives_one_fit_per_scan(small):
    r = np.random.default_rng(0).normal(size=small.n)
    fits = estimate_noise(small, r, scope="per-scan")
    assert sorted(fits) == [0, 1]
    assert all(f.best.n_pairs < sum(ff.best.n_pairs for ff in fits.values()) for f in fits.values())
    with pytest.raises(NoiseModelError, match="scope"):
        estimate_noise(small, r, scope="global")


def test_detrend_removes_a_plane():
    # white noise plus a steep per-scan plane: without detrending the variogram rises with
    # the lag (a linear term), with a linear detrend it is flat at sigma^2 (noise 0.1 mm,
    # 2000 points: the bin means scatter by a few per cent, the shortest bins' more; over
    # 20 seeds the worst bin lay 3-18 % off, so 25 %)
    sample = phantom_sample(1000, 2, seed=1)
    rng = np.random.default_rng(3)
    r = 0.1 * rng.normal(size=sample.n) + 0.02 * sample.points_mm[:, 0]
    raw = empirical_variogram(sample, r)
    flat = empirical_variogram(sample, r, detrend="linear")
    assert raw.gamma_mm2[-1] > 3 * raw.gamma_mm2[0]
    assert flat.gamma_mm2 == pytest.approx(np.full_like(flat.gamma_mm2, 0.01), rel=0.25)
    with pytest.raises(NoiseModelError, match="detrend"):
        empirical_variogram(sample, r, detrend="cubic")


def test_short_range_fit_resists_a_large_scale_misfit():
    # a p2 pattern of 0.4 sigma on 5 mm noise: the short-range (40 mm) estimate stays
    # near the noise (bench: length ratio 1.14, 10-90 % 0.95-1.36); all lags lengthen it,
    # the misfit taken for noise: this draw 2.6 times (review CF-25: "doubles" was said,
    # "longer" checked; over 30 other seeded draws the factor's median is 1.6, its 10-90 %
    # 1.1-2.9, so 1.5 is asked of this draw)
    sample = phantom_sample(2000, 1, seed=0)
    truth = NoiseModel("exponential", 0.3, 0.0, 5.0)
    J = sag_sensitivity(sample)
    x = NoiseSampler.of(sample, truth).draw(np.random.default_rng(4))[:, 0]
    x = x + 0.4 * 0.3 * misfit_pattern(sample)
    r = x - J * (J @ x) / (J @ J)
    short = estimate_noise(sample, r).best
    long = estimate_noise(sample, r, max_lag_mm=150.0).best
    assert short.length_mm < 1.6 * 5.0
    assert long.length_mm > 1.5 * short.length_mm


def test_noise_model_rejects_bad_parameters():
    with pytest.raises(NoiseModelError, match="sigma_mm"):
        NoiseModel("exponential", 0.0, 0.0, 1.0)
    with pytest.raises(NoiseModelError, match="nugget_fraction"):
        NoiseModel("exponential", 1.0, 1.5, 1.0)
    with pytest.raises(NoiseModelError, match="length_mm"):
        NoiseModel("exponential", 1.0, 0.0, -1.0)
    with pytest.raises(NoiseModelError, match="unknown kernel"):
        NoiseModel("spherical", 1.0, 0.0, 1.0)


# ------------------------------------------------------------------------- covariances


def test_covariance_is_block_diagonal_with_the_nugget_on_the_diagonal(small):
    m = NoiseModel("matern32", 0.4, 0.25, 6.0)
    c = covariance_matrix(small, m)
    a, b = small.blocks
    assert np.all(c[np.ix_(a, b)] == 0.0)
    assert np.diag(c) == pytest.approx(np.full(small.n, 0.16), rel=1e-14)
    d = np.linalg.norm(small.points_mm[a[0]] - small.points_mm[a[1]])
    assert c[a[0], a[1]] == pytest.approx(0.16 * 0.75 * correlation("matern32", d, 6.0), rel=1e-12)
    np.testing.assert_allclose(m.covariance(small.points_mm[b]), c[np.ix_(b, b)], rtol=1e-14)


def test_chunked_covariance_matches_dense(small, monkeypatch):
    m = {0: NoiseModel("exponential", 0.3, 0.1, 5.0), 1: NoiseModel("gaussian", 0.2, 0.0, 9.0)}
    x = np.random.default_rng(0).normal(size=(small.n, 3))
    dense = apply_covariance(small, m, x)
    assert dense == pytest.approx(covariance_matrix(small, m) @ x, rel=1e-12, abs=1e-14)
    monkeypatch.setattr(noise_mod, "MAX_DENSE_BLOCK", 100)
    monkeypatch.setattr(noise_mod, "CHUNK", 128)
    assert apply_covariance(small, m, x) == pytest.approx(dense, rel=1e-12, abs=1e-14)


def test_whitener_gives_identity_covariance(small):
    m = NoiseModel("exponential", 0.3, 0.2, 7.0)
    w = whitener(small, m)
    c = covariance_matrix(small, m)
    white = w.apply(w.apply(c).T).T  # L^-1 Sigma L^-T
    np.testing.assert_allclose(white, np.eye(small.n), atol=1e-8)  # jitter 1e-10, cond ~1e2
    _, logdet = np.linalg.slogdet(c)
    assert w.logdet() == pytest.approx(logdet, rel=1e-9)


def test_dense_paths_refuse_huge_scans(small, monkeypatch):
    monkeypatch.setattr(sample_mod, "MAX_DENSE_BLOCK", 100)
    with pytest.raises(SampleError, match="limited to 100"):
        SurfaceSample(small.points_mm, small.scan).distances(0)


def test_local_counts_are_correlation_row_sums(small):
    m = NoiseModel("gaussian", 0.3, 0.3, 4.0)
    counts = local_counts(small, m)
    c = covariance_matrix(small, m)
    assert counts == pytest.approx(c.sum(axis=1) / 0.09, rel=1e-12)
    # the variance of each scan mean is sigma^2 / n_eff(scan): sum of the two scans
    n_eff = sum(0.09 * len(idx) ** 2 / c[np.ix_(idx, idx)].sum() for idx in small.blocks)
    assert effective_sample_count(small, m) == pytest.approx(n_eff, rel=1e-12)
    assert effective_sample_count(small, NoiseModel("gaussian", 0.3, 1.0, 0.0)) == small.n


@pytest.mark.parametrize("kernel", ["exponential", "gaussian"])
def test_local_count_approximation_against_exact_whitening(kernel):
    # item 5: x' Sigma^-1 x ~ sum x^2 / (sigma^2 m) for fields smooth on the noise's
    # scale. On 2000 points with l = 2 mm (where it is meant to be used: short-range
    # imaging noise) the bench's effective table measures -2.4 to -6 %; asserted < 8 %.
    # At 20 mm it is off by 20-55 % (documented, not used there).
    sample = phantom_sample(2000, 1, seed=0)
    m = NoiseModel(kernel, 0.3, 0.0, 2.0)
    w = whitener(sample, m)
    counts = local_counts(sample, m)
    for x in (sag_sensitivity(sample), misfit_pattern(sample), misfit_pattern(sample, kind="tilt")):
        exact = float(np.sum(w.apply(x) ** 2))
        approx = float(np.sum(x * x / (0.09 * counts)))
        assert approx == pytest.approx(exact, rel=0.08)


def test_session_noise_measures_each_scan_s_level_and_gives_it_where_asked():
    # three scans of 300, 500 and 700 points of one correlation (exponential 3 mm, nugget
    # 0.3), sds 0.05, 0.05 and 0.15 mm (one scan imaged coarser or noisier: review W),
    # and 0.08 each. The levels come from the shortest lags, relative to the quietest
    # scan's: over 40 draws of equal scans their spread was 5-7 % of the level, so 20 %
    # is 3 spreads
    from calib.stats.coverage import NoiseSampler
    from calib.stats.noise import session_noise, with_sigma

    full = phantom_sample(700, 3, seed=5)
    idx = np.concatenate([b[:n] for b, n in zip(full.blocks, (300, 500, 700), strict=True)])
    sample = SurfaceSample(full.points_mm[idx], full.scan[idx])
    shape = NoiseModel("exponential", 1.0, 0.3, 3.0)
    rng = np.random.default_rng(1)
    for sds in ((0.05, 0.05, 0.15), (0.08, 0.08, 0.08)):
        draw = NoiseSampler.of(sample, {k: with_sigma(shape, s) for k, s in enumerate(sds)})
        for by_scan in (False, True):
            r = draw.draw(rng)[:, 0]
            fit = session_noise(sample, r, by_scan=by_scan)
            levels = np.array([fit.scan_sd_mm[k] for k in range(3)])
            np.testing.assert_allclose(levels, sds, rtol=0.2)
            assert fit.by_scan is by_scan
            arg = fit.best_arg
            if not fit.by_scan:
                assert arg is fit.best and fit.alternatives == tuple(fit.plausible[1:])
                continue
            # each scan: the session's correlation at its own level, the truth's ratios
            ratios = [arg[k].sigma_mm / arg[0].sigma_mm for k in range(3)]
            np.testing.assert_allclose(ratios, np.array(sds) / sds[0], rtol=0.2)
            assert all(arg[k].length_mm == fit.best.length_mm for k in range(3))
            # each scan's own fit is one more alternative
            assert fit.alternatives[-1] == dict(fit.scan_fits)
            # the floor: the mean over the points (scans of 300, 500 and 700)
            n = np.array([300, 500, 700])
            sigma2 = np.array([arg[k].sigma_mm ** 2 for k in range(3)])
            assert fit.variance_mm2(sample) == pytest.approx(n @ sigma2 / n.sum())
            # a variance's spread is twice its level's (10-14 %): 40 % is 3 of those
            assert fit.variance_mm2(sample) == pytest.approx(n @ np.square(sds) / n.sum(), rel=0.4)
