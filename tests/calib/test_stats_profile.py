"""The residual's spread by height band (calib.stats.profile)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.stats import HeightProfile, height_profile
from calib.stats.profile import HEIGHT_BANDS_MM


def _sd_at(h):
    # a spread three times the far one at the plate, falling to it by 30 mm
    return 0.1 * np.interp(h, [0.0, 5.0, 12.0, 30.0], [3.0, 3.0, 1.6, 1.0])


def test_a_known_profile_is_recovered():
    rng = np.random.default_rng(0)
    h = rng.uniform(0.0, 80.0, 60_000)
    r = rng.normal(0.0, _sd_at(h)) + 0.3  # an offset is not spread
    prof = height_profile(h, r)
    edges = np.asarray(HEIGHT_BANDS_MM)
    mid = 0.5 * (edges[:-1] + np.minimum(edges[1:], 80.0))
    counts = np.asarray(prof.counts)
    # the truth per band: the rms of sd(h) over the band relative to the far band's
    truth = []
    for lo, hi in zip(edges[:-1], np.minimum(edges[1:], 80.0), strict=True):
        hh = np.linspace(lo, hi, 201)
        truth.append(np.sqrt(np.mean(_sd_at(hh) ** 2)))
    truth = np.asarray(truth) / truth[-1]
    # tolerance: the MAD's sd is 1.17 sd / sqrt(n) for a Gaussian (asymptotic relative
    # efficiency 0.37); with the smallest band's n (>= 2,000) a ratio of two scales is
    # within 1.17 sqrt(2 / 2000) = 3.7 % at one sd; 12 % is beyond 3 sd; a band's mixture of
    # spreads is not Gaussian either, which the truth's rms neglects (a few %)
    assert counts.min() >= 2_000
    assert np.allclose(prof.relative_sd, truth, rtol=0.12), (prof.relative_sd, truth, mid)
    assert prof.far_sd_mm == pytest.approx(0.1, rel=0.05)  # 1.17 / sqrt(37500) = 0.6 % sd
    # weights undo the spread: the weighted residual's spread no longer grows at the plate
    # (the weights carry a band's 3.7 % error at one sd, and each std of >= 2,000 points
    # its own sqrt(1 / 2n) = 1.6 %: about 4 % together, so 10 % is 2.5 of them)
    w = prof.weights(h)
    near, far = h < 8.0, h >= 30.0
    assert np.std(r[near] * w[near]) == pytest.approx(np.std(r[far] * w[far]), rel=0.1)


def test_the_profile_never_falls_toward_the_plate_nor_below_one():
    rng = np.random.default_rng(1)
    h = rng.uniform(0.0, 60.0, 20_000)
    # a band at 12-16 mm quieter than the far one, and one at 5-8 mm quieter than 8-12
    sd = np.select([h < 5, h < 8, h < 12, h < 16], [0.3, 0.12, 0.2, 0.05], 0.1)
    prof = height_profile(h, rng.normal(0.0, sd))
    rel = np.asarray(prof.relative_sd)
    assert np.all(np.diff(rel) <= 0.0) and np.all(rel >= 1.0)
    # 12-16 mm, quieter than far, takes the next band out's value (16-20 mm, as loud as
    # far: 1 within its 4 % sampling sd at n = 1,300)
    assert rel[3] == rel[4] == pytest.approx(1.0, abs=0.12)
    assert rel[1] == pytest.approx(rel[2])  # 5-8 mm takes the larger 8-12 mm value
    assert rel[0] == pytest.approx(3.0, rel=0.1)  # 2 % sd at n = 1,700


def test_a_thin_band_takes_the_value_of_the_next_band_out():
    rng = np.random.default_rng(2)
    h = np.concatenate([rng.uniform(5.0, 60.0, 10_000), [1.0, 2.0, 3.0]])  # 3 points < 5 mm
    r = rng.normal(0.0, np.where(h < 12.0, 0.2, 0.1))
    prof = height_profile(h, r)
    assert prof.counts[0] == 3
    assert prof.relative_sd[0] == prof.relative_sd[1]
    assert prof.scale(np.array([0.0, 4.9])).tolist() == [prof.relative_sd[0]] * 2


def test_scale_weights_and_json():
    prof = HeightProfile((0.0, 5.0, np.inf), (2.0, 1.0), (40, 400), 0.1)
    assert prof.scale(np.array([0.0, 4.99, 5.0, 100.0])).tolist() == [2.0, 2.0, 1.0, 1.0]
    assert prof.weights(np.array([1.0, 50.0])).tolist() == [0.5, 1.0]
    assert prof.as_json() == {"edges_mm": [0.0, 5.0, None], "relative_sd": [2.0, 1.0],
                              "counts": [40, 400], "far_sd_mm": 0.1}  # fmt: skip


def test_bad_input_says_what_is_wrong():
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        height_profile(np.zeros(5), np.zeros(4))
    with pytest.raises(ValueError, match="increase from 0 to inf"):
        height_profile(np.zeros(5), np.zeros(5), edges_mm=(0.0, 10.0, 5.0, np.inf))
    with pytest.raises(ValueError, match="no height band holds 30"):
        height_profile(np.arange(10.0), np.ones(10))
    with pytest.raises(ValueError, match="no spread"):
        height_profile(np.full(100, 50.0), np.ones(100))
