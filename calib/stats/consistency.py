"""Posture consistency: the test that every scan asks for the same c1.

A model that fits is fitted by every posture alike: fitted to one scan alone, each scan
would give the same ``ln c1`` up to its noise. A missing effect changes the apparent
stiffness with the loading (a stiff skin, a membrane, matters more where the gland hangs
than where it is tilted), so the scans disagree. This is the over-identification test of
a model fitted to a subset (the calibration scans) and checked on the rest, in the form
of a meta-analysis heterogeneity test.

Per scan ``k`` (one label of the sample), the residual at the calibrated ``theta`` is
regressed on ``[J_k, 1]`` (``J_k = dr/dtheta`` and a constant normal offset of the whole
scan: segmentation threshold and mesh faceting, about +0.1 mm on the twins, are no
change of stiffness). The one Gauss-Newton step gives the scan's own estimate
``theta_k`` and, under the noise model, its series interval
(:func:`calib.stats.parameter_intervals`, measured coverage 93.5-96.0 % of nominal 95 %);
``se_k`` is that interval's half-width over 1.959964, the normal-equivalent standard
error, so the series estimator's heavier tails (its Imhof quantile) stay in the test.
Cochran's (1954) heterogeneity statistic

    Q = sum_k w_k (theta_k - theta_bar)^2,  w_k = 1 / se_k^2,
    theta_bar = sum_k w_k theta_k / sum_k w_k,

is chi-square with ``K - 1`` degrees of freedom when the scans' noises are independent
and the model fits (its false-alarm rate on correlated noise is measured in
``tests/calib/test_stats_consistency.py``).

The noise model is the session's (:func:`calib.stats.noise.session_noise`): the
least-disturbed scan's short-range fit, applied to every scan. A scan's own variogram
would absorb a smooth misfit as long-range noise (22 mm on the hidden-skin twin's
lateral scan against 3 mm on its tilted ones) and widen exactly the interval the test
needs narrow.

Not in the test: the model mesh's discretisation error. It moves every scan's estimate,
mostly alike (a mesh too stiff is too stiff in every posture); on the quick ``--effect
none`` twins the scans' estimates differ by at most 1.4 % over three seeds (``python
benchmarks/bench_calib.py --effect none --seeds 0,1,2``, then the ``postures`` block of
each ``calibration.json``).

References
----------
Cochran, W. G. (1954). The combination of estimates from different experiments.
*Biometrics* 10, 101-129.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .intervals import IntervalError, _json_number, parameter_intervals
from .noise import MAX_LAG_MM, NoiseFit, session_noise
from .sample import SurfaceSample

__all__ = [
    "POSTURE_ALPHA",
    "ConsistencyError",
    "PostureConsistency",
    "ScanEstimate",
    "posture_consistency",
]

#: False-alarm rate of the posture-consistency test. With the misfit test's
#: :data:`calib.stats.scores.MISFIT_ALPHA` (0.01), ``calibrate``'s ``model_fit`` verdict's
#: false-alarm rate is at most :data:`calib.stats.scores.SCREEN_ALPHA` (Bonferroni).
POSTURE_ALPHA = 0.04

#: Normal 97.5 % quantile: a 95 % interval's half-width over this is its standard error.
Z_975 = 1.959963984540054


class ConsistencyError(ValueError):
    """Fewer than two scans, or residuals that give no scan estimate."""


@dataclass(frozen=True)
class ScanEstimate:
    """One scan's own estimate of ``theta`` (one Gauss-Newton step from the fit).

    Attributes
    ----------
    label : int
        The scan's label in the sample.
    theta : float
        ``theta_k`` (units of theta; ``ln c1`` with c1 in Pa for the calibration).
    standard_error : float
        Normal-equivalent standard error (95 % series half-width / 1.96).
    offset_mm : float
        The scan's fitted constant normal offset.
    n_points : int
    """

    label: int
    theta: float
    standard_error: float
    offset_mm: float
    n_points: int


@dataclass(frozen=True)
class PostureConsistency:
    """Result of :func:`posture_consistency`.

    Attributes
    ----------
    estimates : tuple of ScanEstimate
        In the order of the sample's labels.
    theta_bar : float
        The precision-weighted mean of the scans' estimates.
    statistic : float
        Cochran's Q.
    dof : int
        ``K - 1``.
    p_value : float
    alpha : float
    verdict : str
        ``"consistent"`` or ``"inconsistent"`` (``p_value < alpha``).
    noise : dict
        The noise model used, as JSON.
    """

    estimates: tuple[ScanEstimate, ...]
    theta_bar: float
    statistic: float
    dof: int
    p_value: float
    alpha: float
    verdict: str
    noise: dict

    def as_json(self, names: dict[int, str] | None = None) -> dict:
        """Plain JSON; ``names`` maps labels to scan names (else the labels as text)."""
        names = names or {}
        scans = {
            names.get(e.label, str(e.label)): {
                "theta": _json_number(e.theta),
                "standard_error": _json_number(e.standard_error),
                "offset_mm": _json_number(e.offset_mm),
                "n_points": e.n_points,
            }
            for e in self.estimates
        }
        return {
            "test": "Cochran Q of the scans' own estimates",
            "statistic": _json_number(self.statistic),
            "dof": self.dof,
            "p_value": _json_number(self.p_value),
            "alpha": self.alpha,
            "verdict": self.verdict,
            "theta_bar": _json_number(self.theta_bar),
            "scans": scans,
            "noise": self.noise,
        }


def _scan_estimate(theta, label, r, J, pts, noise: NoiseFit) -> ScanEstimate:
    """One scan's Gauss-Newton step on ``[J, 1]`` and its series interval."""
    A = np.column_stack([J, np.ones_like(J)])
    step, *_ = np.linalg.lstsq(A, -r, rcond=None)
    r_k = r + A @ step
    try:
        (iv, _) = parameter_intervals(
            [theta + step[0], step[1]],
            A,
            r_k,
            SurfaceSample(pts),
            noise.best,
            alternatives=tuple(noise.plausible[1:]),
        )
    except IntervalError as exc:
        raise ConsistencyError(f"scan {label}: no interval of its own estimate ({exc})") from exc
    se = (iv.upper - iv.lower) / (2.0 * Z_975)
    return ScanEstimate(int(label), float(theta + step[0]), float(se), float(step[1]), len(r))


def posture_consistency(
    theta: float,
    residual_mm: np.ndarray,
    jacobian: np.ndarray,
    sample: SurfaceSample,
    noise: NoiseFit | None = None,
    *,
    alpha: float = POSTURE_ALPHA,
    seed: int = 0,
    max_lag_mm: float = MAX_LAG_MM,
) -> PostureConsistency:
    """Test whether every scan, fitted alone, asks for the same ``theta``.

    Parameters
    ----------
    theta : float
        The fitted parameter (``ln c1``, c1 in Pa).
    residual_mm : ndarray, shape (n,)
        Residuals of every scan at ``theta`` (measured minus simulated, mm).
    jacobian : ndarray, shape (n,)
        ``dr / dtheta`` (mm per unit of theta).
    sample : SurfaceSample
        The residuals' points, one label per scan (at least two scans).
    noise : NoiseFit, optional
        The noise model applied to every scan. Default: the session's
        (:func:`calib.stats.noise.session_noise`), fitted on the residuals less each
        scan's mean (the offset every scan's own fit takes out).
    alpha : float
        False-alarm rate of the verdict.
    seed : int
        Seed of the variogram's pair sample (default noise model only).
    max_lag_mm : float
        The variogram's reach (default noise model only; mm): sized for a twin-tall body,
        :func:`calib.evaluation.check_postures` scales it with the body's height.

    Returns
    -------
    PostureConsistency

    Raises
    ------
    ConsistencyError
        Fewer than two scans, ``alpha`` outside (0, 1), or a scan whose estimate has no
        interval (its residual does not change with ``theta``).
    """
    from scipy import stats

    if not 0.0 < alpha < 1.0:
        raise ConsistencyError(f"alpha must lie in (0, 1), got {alpha}")
    if len(sample.labels) < 2:
        raise ConsistencyError(
            f"posture consistency needs at least two scans, got {len(sample.labels)}"
        )
    r = sample.check_values(residual_mm, "residual_mm")
    J = sample.check_values(jacobian, "jacobian")
    if noise is None:
        offsets = np.zeros_like(r)
        for idx in sample.blocks:
            offsets[idx] = r[idx].mean()
        noise = session_noise(sample, r - offsets, seed=seed, max_lag_mm=max_lag_mm)
    est = tuple(
        _scan_estimate(float(theta), lab, r[idx], J[idx], sample.points_mm[idx], noise)
        for lab, idx in zip(sample.labels, sample.blocks, strict=True)
    )
    th = np.array([e.theta for e in est])
    w = 1.0 / np.array([e.standard_error for e in est]) ** 2
    bar = float(w @ th / w.sum())
    q = float(w @ (th - bar) ** 2)  # Cochran (1954)
    dof = len(est) - 1
    p = float(stats.chi2.sf(q, dof))
    verdict = "inconsistent" if p < alpha else "consistent"
    return PostureConsistency(est, bar, q, dof, p, alpha, verdict, noise.best.as_json())
