"""A ``fits`` verdict whose noise model ended on its length bound says it cannot tell.

A smooth 0.3 mm misfit over a 60 mm dome with 0.02 mm of white noise: the variogram does
not level off, the fitted correlation length ends at its search bound (``NoiseModel.
length_at_bound``), the band-F ratio takes the smooth field for noise and says ``fits``
(p ~ 0.97, audit E item 4). The flag was computed and never said; now the progress line
and the summary say that this test cannot tell a smooth misfit from noise here.
"""

from __future__ import annotations

import numpy as np

from calib.fitting.pipeline import LENGTH_AT_BOUND_NOTE, _model_fit_line
from calib.fitting.uncertainty import series_uncertainty
from calib.report.tables import _model_fit_lines


def _dome(n: int, radius_mm: float, rng) -> np.ndarray:
    u = rng.uniform(np.cos(np.radians(70.0)), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    s = np.sqrt(1.0 - u**2)
    return radius_mm * np.column_stack([s * np.cos(phi), s * np.sin(phi), u])


def test_a_smooth_misfit_taken_for_noise_is_said():
    rng = np.random.default_rng(1)
    p = _dome(1500, 60.0, rng)
    x = p / 60.0
    dr = 10.0 * x[:, 2] + 2.0 * x[:, 0]  # mm per unit ln c1
    r = 0.3 * np.sin(2.0 * x[:, 0]) * np.cos(1.5 * x[:, 1]) + 0.02 * rng.standard_normal(len(p))
    r -= dr * (dr @ r) / (dr @ dr)  # at the least-squares optimum
    _, fit = series_uncertainty(420.0, r, dr, p, np.zeros(len(p), dtype=np.int64))
    assert fit.verdict == "fits" and fit.noise.length_at_bound
    assert LENGTH_AT_BOUND_NOTE in _model_fit_line(fit)
    lines = _model_fit_lines(fit.as_json(), None)
    assert any("ended at the search bound" in line for line in lines)


def test_white_noise_alone_gets_no_note():
    rng = np.random.default_rng(2)
    p = _dome(1500, 60.0, rng)
    dr = 10.0 * p[:, 2] / 60.0
    r = 0.2 * rng.standard_normal(len(p))
    r -= dr * (dr @ r) / (dr @ dr)
    _, fit = series_uncertainty(420.0, r, dr, p, np.zeros(len(p), dtype=np.int64))
    assert not fit.noise.length_at_bound
    assert "search bound" not in _model_fit_line(fit)
    assert not any("search bound" in line for line in _model_fit_lines(fit.as_json(), None))
