"""Goodness of fit and effect screening on surface residuals with correlated noise.

Misfit test (:func:`misfit_test`). Under the null the residual at the fit is noise with
whatever the fitted parameters absorb removed: ``r = M eps``. A model that misses an
effect (a stiff skin absorbed into c1) leaves a smooth, large-scale pattern. The
residual is projected on smooth per-scan modes orthogonal to ``J`` (polynomials in the
scan's coordinates, :mod:`calib.stats.modes`): a *low* band (degree <= 2, the scale of a
missed effect) and a *high* band (degree 3-4). With ``Omega`` their covariance under the
short-range noise model and ``z = L^{-1} u`` (``Omega = L L'``, low band first), the
score (Lagrange multiplier, Rao 1948) statistic of "the low-band modes have zero mean"
is ``|z_low|^2 ~ chi2(K_low)`` if the noise model were exact. It is not: the variance of
large-scale projections of correlated noise rests on the model's long-range
extrapolation (see :mod:`calib.stats.intervals`), and a short-range fit of one residual
gets its overall level wrong by tens of per cent where the noise is correlated over
~10-20 mm. The default statistic is therefore the band ratio
``F = (|z_low|^2 / K_low) / (|z_high|^2 / K_high) ~ F(K_low, K_high)``: the noise level
cancels, only the model's spectral shape between the bands is used. ``method="chi2"``
gives the plain whitened score test (more power, less robust; both are measured by
``benchmarks/bench_coverage.py --table misfit``).

Effect screening (:func:`screen_effects`, issue 13). For a candidate effect with
sensitivity field ``s_k = dr / d beta_k`` the score at the fitted parameters is
``s_k' r``; with what ``J`` absorbs projected out, the one-step estimate
``beta_k = s~_k' r / |s~_k|^2`` (``s~ = M s``) is Rao's score statistic rescaled. It is
normalised by the series variance of :mod:`calib.stats.intervals` computed on the
augmented design ``[J, s_k]``, so a smooth effect is not judged against a noise level
that the noise model extrapolates; the p-value is the exact tail of the ratio under the
model (Imhof). An effect whose neutral value is an end of its physical range (a
Mooney c2 cannot be negative, a plate cannot be held tighter than clamped) is tested
against its one-sided alternative (Silvapulle & Silvapulle 1995, a score test against
one-sided alternatives): the ratio's null distribution is symmetric, so the one-sided
p-value is half the two-sided one when the estimate points the physical way and one
minus that half when it does not. Holm (1979) controls the family-wise error across
effects, not columns: an effect with several columns (a gravity-direction error has two
angles per scan, a rigid offset six) is one hypothesis, "all its columns are zero", tested
by its smallest p-value times its number of tested columns (Bonferroni within the
effect, a valid joint test that needs no joint null law); Holm then runs over the
effects. A column is reported significant when its effect is and its own within-effect
Bonferroni p is below ``alpha`` too. The
projection also tells up front what the data cannot separate: in the metric of the noise
model (whitened), the fraction of ``s_k`` that survives projection off ``J``
(``retained_fraction``; below ``min_retained`` the effect is "not identifiable from
these data") and the cosine between two effects' projected whitened signatures
(``|cos|`` above ``confounded_above``: confounded). Each tested column also reports the
size it would find with 80 % power (:func:`detectable_size`) at its Bonferroni level,
``alpha`` over the number of tested effects and the effect's tested columns (Holm's
first step, so a bound for the step-down), from the observed series standard error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .intervals import (
    IntervalError,
    SeriesStatistic,
    _jacobian,
    _json_number,
    _models,
    _shown,
    series_design,
    series_statistic,
)
from .modes import orthonormalise, scan_polynomials
from .noise import NoiseArg, NoiseModel, _model_for, apply_covariance, local_counts, whitener
from .quadform import Quantile, ratio_critical_value, ratio_tail
from .sample import MAX_DENSE_BLOCK, SurfaceSample

__all__ = [
    "MISFIT_ALPHA",
    "SCREEN_ALPHA",
    "EffectScore",
    "EffectScreening",
    "ModelFit",
    "ScreeningError",
    "detectable_size",
    "holm",
    "misfit_test",
    "screen_effects",
    "signature_geometry",
]


#: Level of the model-misfit (band-F) test, in calibrate's ``model_fit`` and diagnose's
#: screens: a model is called misfit only on strong evidence.
MISFIT_ALPHA = 0.01
#: Family-wise level of the effect screening (Holm across effects), diagnose's
#: ``--alpha``; calibrate's two model tests share it (misfit + posture, Bonferroni:
#: :data:`calib.stats.consistency.POSTURE_ALPHA`).
SCREEN_ALPHA = 0.05


class ScreeningError(ValueError):
    """Sensitivity fields or names that do not fit the residuals."""


def _check_not_absorbed(r: np.ndarray, J: np.ndarray) -> None:
    """Refuse a residual the fitted columns explain exactly (review AV).

    Its statistics would be ratios of round-off (every draw of such residuals screened
    some effect significant) or a division by zero.
    """
    q, _ = np.linalg.qr(J)
    size = float(np.linalg.norm(r))
    rest = float(np.linalg.norm(r - q @ (q.T @ r)))
    if not rest > 1e-10 * size:  # a zero residual too
        raise ScreeningError(
            f"the residual (norm {size:.3g} mm) has no part that the fitted columns do not "
            f"explain ({rest:.3g} mm left): an exact fit leaves nothing to test"
        )


# ------------------------------------------------------------------------ misfit test


@dataclass(frozen=True)
class ModelFit:
    """Result of :func:`misfit_test`, ready for ``calibration.json``'s ``model_fit``.

    Attributes
    ----------
    statistic : float
        ``F`` (``method="band-F"``) or ``chi2`` (``method="chi2"``).
    dof : tuple of float
        ``(K_low, K_high)`` for F, ``(K_low,)`` for chi2.
    p_value : float
        Under the noise model (the largest over plausible models).
    verdict : {"fits", "misfit"}
        ``"misfit"`` when ``p_value < alpha``.
    method : str
    alpha : float
    chi2_statistic, chi2_p_value : float
        The plain whitened score test on ``K_low`` degrees of freedom (``chi2_dof`` in
        :meth:`as_json`), always reported; with ``method="band-F"`` it is not in the
        verdict (it needs the noise model's variance exact, which the F ratio does not).
    low_degree, high_degree : int
    noise : NoiseModel
    """

    statistic: float
    dof: tuple[float, ...]
    p_value: float
    verdict: Literal["fits", "misfit"]
    method: str
    alpha: float
    chi2_statistic: float
    chi2_p_value: float
    low_degree: int
    high_degree: int
    noise: NoiseModel

    def as_json(self) -> dict:
        """``{statistic, dof, p_value, verdict, ...}`` in plain JSON types."""
        return {
            "statistic": float(self.statistic),
            "dof": [float(d) for d in self.dof],
            "p_value": float(self.p_value),
            "verdict": self.verdict,
            "method": self.method,
            "alpha": float(self.alpha),
            "chi2_statistic": float(self.chi2_statistic),
            "chi2_p_value": float(self.chi2_p_value),
            "chi2_dof": float(self.dof[0]),  # K_low, in either method
            "low_degree": int(self.low_degree),
            "high_degree": int(self.high_degree),
            "noise": self.noise.as_json(),
        }


@dataclass(frozen=True, eq=False)
class MisfitDesign:
    """Geometry-only part of :func:`misfit_test`: orthonormal band modes.

    Attributes
    ----------
    sample : SurfaceSample
    modes : ndarray, shape (n, K_low + K_high)
        Orthonormal, orthogonal to ``J``; the low band first.
    n_low : int
    low_degree, high_degree : int
    """

    sample: SurfaceSample
    modes: np.ndarray
    n_low: int
    low_degree: int
    high_degree: int


def misfit_design(
    sample: SurfaceSample, jacobian: np.ndarray, *, low_degree: int = 2, high_degree: int = 4
) -> MisfitDesign:
    """Low- and high-band smooth modes orthogonal to the fitted parameters' ``J``.

    Parameters
    ----------
    sample : SurfaceSample
    jacobian : ndarray, shape (n,) or (n, p)
    low_degree, high_degree : int
        Bands ``0..low_degree`` and ``low_degree + 1..high_degree`` (per scan).

    Returns
    -------
    MisfitDesign
    """
    if not 0 <= low_degree < high_degree:
        raise ScreeningError(f"need 0 <= low_degree < high_degree, got {low_degree}, {high_degree}")
    J = _jacobian(sample, jacobian)
    phi, deg = scan_polynomials(sample, high_degree)
    order = np.argsort(deg > low_degree, kind="stable")  # every scan's low band first
    q, kept = orthonormalise(phi[:, order], against=J)
    n_low = int(np.sum(deg[order][kept] <= low_degree))
    if n_low == 0 or n_low == q.shape[1]:
        raise ScreeningError(f"a band is empty after projection ({n_low} of {q.shape[1]} low)")
    return MisfitDesign(sample, q, n_low, low_degree, high_degree)


def _band_stats(design: MisfitDesign, u: np.ndarray, noise: NoiseArg) -> tuple[float, float]:
    """``(|z_low|^2, |z_high|^2)`` whitened under ``noise``."""
    b = design.modes
    om = b.T @ apply_covariance(design.sample, noise, b)
    L = np.linalg.cholesky(0.5 * (om + om.T))
    z = np.linalg.solve(L, u)
    k = design.n_low
    return float(z[:k] @ z[:k]), float(z[k:] @ z[k:])


def misfit_test(
    residual_mm: np.ndarray,
    jacobian: np.ndarray,
    sample: SurfaceSample,
    noise: NoiseArg,
    *,
    alpha: float = MISFIT_ALPHA,
    method: Literal["band-F", "chi2"] = "band-F",
    low_degree: int = 2,
    high_degree: int = 4,
    alternatives: tuple[NoiseArg, ...] = (),
    design: MisfitDesign | None = None,
) -> ModelFit:
    """Test whether the residual holds large-scale structure the noise model cannot explain.

    Parameters
    ----------
    residual_mm : ndarray, shape (n,)
        Residuals at the fit.
    jacobian : ndarray, shape (n,) or (n, p)
        ``dr / dtheta`` at the fit (what the fitted parameters absorb).
    sample : SurfaceSample
    noise : NoiseModel or mapping of scan label to NoiseModel
        The short-range noise model (:func:`calib.stats.noise.estimate_noise`).
    alpha : float
        False-alarm rate of the verdict.
    method : {"band-F", "chi2"}
        See the module docstring.
    low_degree, high_degree : int
    alternatives : tuple
        Other plausible noise models; the largest p-value is used.
    design : MisfitDesign, optional
        Precomputed by :func:`misfit_design` (repeated tests on one geometry).

    Returns
    -------
    ModelFit

    Raises
    ------
    ScreeningError
        ``alpha`` outside (0, 1), ``method`` unknown, ``low_degree``/``high_degree`` not
        ``0 <= low < high``, a band empty after projection, or a residual that the fitted
        columns explain exactly.
    IntervalError
        The Jacobian has rank < p.
    SampleError
        ``residual_mm`` or ``jacobian`` has not one finite row per point of ``sample``.
    """
    from scipy import stats

    if not 0.0 < alpha < 1.0:
        raise ScreeningError(f"alpha must lie in (0, 1), got {alpha}")
    if method not in ("band-F", "chi2"):
        raise ScreeningError(f"method must be 'band-F' or 'chi2', got {method!r}")
    d = design or misfit_design(sample, jacobian, low_degree=low_degree, high_degree=high_degree)
    r = sample.check_values(residual_mm, "residual_mm")
    _check_not_absorbed(r, _jacobian(sample, jacobian))
    u = d.modes.T @ r
    k_lo, k_hi = d.n_low, d.modes.shape[1] - d.n_low
    best = None
    for model in _models(noise, alternatives):
        lo, hi = _band_stats(d, u, model)
        f = (lo / k_lo) / (hi / k_hi)
        p_f = float(stats.f.sf(f, k_lo, k_hi))
        p_c = float(stats.chi2.sf(lo, k_lo))
        p = p_f if method == "band-F" else p_c
        if best is None or p > best[0]:
            best = (p, f, lo, p_c, model)
    p, f, lo, p_c, model = best
    stat, dof = (f, (float(k_lo), float(k_hi))) if method == "band-F" else (lo, (float(k_lo),))
    verdict = "misfit" if p < alpha else "fits"
    return ModelFit(float(stat), dof, float(p), verdict, method, alpha, float(lo), p_c,
                    d.low_degree, d.high_degree, _shown(model))  # fmt: skip


# ------------------------------------------------------------------ effect screening


@dataclass(frozen=True)
class EffectScore:
    """Screening result of one candidate effect.

    Attributes
    ----------
    name : str
    statistic : float
        ``beta_k / se_k``: the score, normalised by its series standard error.
    p_value : float
        Under the noise model (Imhof), largest over plausible models; two-sided or
        against the one-sided alternative (``alternative``).
    p_holm : float
        The larger of the effect's Holm-adjusted p (Holm across the identifiable effects
        of the within-effect Bonferroni p) and this column's within-effect Bonferroni p;
        nan if not identifiable. An effect's p is the smallest over its columns.
    significant : bool
        ``p_holm < alpha``.
    estimate : float
        One-step estimate of the effect parameter (its units; from the neutral value).
    standard_error : float
        Series standard error of ``estimate``.
    plugin_standard_error : float
        ``sqrt(a' Sigma a)`` under the model.
    detectable : float
        Smallest ``|beta|`` (in the units of ``estimate``) found with about 80 % power
        after the family-wise correction, on the data's scale (module docstring,
        :func:`detectable_size`).
    retained_fraction : float
        Whitened norm of ``s_k`` left after projecting off ``J``, over its whole norm.
    identifiable : bool
    dof : float
    n_modes : int
    alternative : {"two-sided", "greater", "less"}
        The alternative tested (``greater``: only estimates above neutral are physical).
    effect : str
        The effect (the family Holm runs over) this column belongs to; ``name`` if alone.
    """

    name: str
    statistic: float
    p_value: float
    p_holm: float
    significant: bool
    estimate: float
    standard_error: float
    plugin_standard_error: float
    detectable: float
    retained_fraction: float
    identifiable: bool
    dof: float
    n_modes: int
    alternative: Literal["two-sided", "greater", "less"] = "two-sided"
    effect: str = ""


#: The alternative of each direction of :func:`screen_effects`.
ALTERNATIVES = {0: "two-sided", 1: "greater", -1: "less"}


def one_sided(p_two_sided: float, t: float, direction: int) -> float:
    """The p-value against a one-sided alternative from a symmetric statistic's two-sided one.

    Parameters
    ----------
    p_two_sided : float
    t : float
        The statistic (its sign is the estimate's).
    direction : {-1, 0, 1}
        The physical sign of a departure; 0 returns ``p_two_sided``.
    """
    if direction == 0:
        return p_two_sided
    half = 0.5 * p_two_sided
    return half if np.sign(t) == direction else 1.0 - half


@dataclass(frozen=True)
class EffectScreening:
    """Result of :func:`screen_effects`.

    Attributes
    ----------
    effects : tuple of EffectScore
        In the order given.
    cosine : ndarray, shape (q, q)
        Cosines of the projected, whitened signatures (nan for unidentifiable effects).
    confounded : tuple of (str, str, float)
        Identifiable pairs with ``|cosine| >= confounded_above``.
    not_identifiable : tuple of str
    alpha : float
    metric : str
        ``"whitened"`` (Cholesky per scan) or ``"local-counts"`` (the effective-sample
        approximation, scans over :data:`calib.stats.sample.MAX_DENSE_BLOCK` points).
    noise : NoiseModel
    """

    effects: tuple[EffectScore, ...]
    cosine: np.ndarray
    confounded: tuple[tuple[str, str, float], ...]
    not_identifiable: tuple[str, ...]
    alpha: float
    metric: str
    noise: NoiseModel

    def as_json(self) -> dict:
        """Plain JSON types (for ``diagnosis.json``)."""
        rows = [{k: _json_number(v) for k, v in vars(e).items()} for e in self.effects]
        return {
            "effects": rows,
            "cosine": np.where(np.isfinite(self.cosine), self.cosine, None).tolist(),
            "confounded": [list(c) for c in self.confounded],
            "not_identifiable": list(self.not_identifiable),
            "alpha": self.alpha,
            "metric": self.metric,
            "noise": self.noise.as_json(),
        }


def holm(p_values: np.ndarray) -> np.ndarray:
    """Holm's (1979) step-down adjusted p-values.

    Parameters
    ----------
    p_values : ndarray, shape (q,)

    Returns
    -------
    ndarray, shape (q,)
        ``p_(i) -> max_{j <= i} min(1, (q - j + 1) p_(j))`` in the sorted order, mapped
        back; reject where adjusted ``< alpha`` (family-wise error <= alpha).
    """
    p = np.asarray(p_values, dtype=float)
    q = len(p)
    order = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, (q - np.arange(q)) * p[order])  # Holm 1979, step-down
    adj = np.maximum.accumulate(adj)
    out = np.empty(q)
    out[order] = adj
    return out


def detectable_size(
    statistic: SeriesStatistic, alpha: float, *, one_sided: bool = False, power: float = 0.8
) -> float:
    """Effect size found with ``power`` by a score test at level ``alpha``.

    The estimate of a present effect ``beta`` is ``beta + a' eps`` and its series standard
    error does not see ``beta`` (the modes are orthogonal to the effect's column), so
    ``T = beta / se + T0`` with ``T0`` the null ratio. The test rejects when ``T > c_a``
    (``c_a`` the ratio's ``1 - alpha`` point, one- or two-sided) and ``P(T0 > -c_p) =
    power`` gives ``beta = (c_a + c_p) se``. Both points are the ratio's Satterthwaite t
    quantiles (within about 1 % of Imhof's for smooth modes,
    :func:`calib.stats.quadform.ratio_critical_value`) and ``se`` is the observed series
    standard error, so the size is on the data's scale, not the noise model's: where the
    residual carries more than noise in the smooth modes, the size grows with it. The
    far tail of a two-sided test is neglected. Measured power at this size:
    ``benchmarks/bench_coverage.py --table screen``.

    Parameters
    ----------
    statistic : SeriesStatistic
        The column's series statistic (:func:`calib.stats.intervals.series_statistic`).
    alpha : float
        Level of the column's test, in (0, 1) (after any multiplicity correction).
    one_sided : bool
        Whether the test is against a one-sided alternative.
    power : float
        In (0.5, 1).

    Returns
    -------
    float
        In the units of the column's estimate.
    """
    tails = 2.0 if one_sided else 1.0  # the two-sided level whose one tail is alpha
    if not 0.0 < tails * alpha < 1.0 or not 0.5 < power < 1.0:
        raise ScreeningError(
            f"need alpha in (0, {1 / tails:g}) and power in (0.5, 1), got {alpha}, {power}"
        )
    om, w = statistic.omega, statistic.weights
    c_a = ratio_critical_value(om, w, level=1.0 - tails * alpha, method="satterthwaite")
    c_p = ratio_critical_value(om, w, level=2.0 * power - 1.0, method="satterthwaite")
    return float((c_a + c_p) * statistic.standard_error)


def _effect_holm(p_values: Sequence[float | None], effects: Sequence[str]) -> np.ndarray:
    """Per column: Holm across effects of the within-effect Bonferroni p (module docstring).

    Parameters
    ----------
    p_values : sequence of float or None, length q
        Each column's p-value; None for a column not tested.
    effects : sequence of str, length q
        The effect of each column.

    Returns
    -------
    ndarray, shape (q,)
        ``max(effect's Holm-adjusted p, min(1, m p_col))`` with ``m`` the effect's number
        of tested columns; nan for untested columns.
    """
    tested = [k for k, p in enumerate(p_values) if p is not None]
    out = np.full(len(p_values), np.nan)
    if not tested:
        return out
    members: dict[str, list[int]] = {}
    for k in tested:
        members.setdefault(effects[k], []).append(k)
    names = list(members)
    # Bonferroni within the effect: m times its smallest p
    joint = np.array(
        [min(1.0, len(members[n]) * min(p_values[k] for k in members[n])) for n in names]
    )
    family = dict(zip(names, holm(joint), strict=True))  # Holm (1979) across effects
    for n in names:
        m = len(members[n])
        for k in members[n]:
            out[k] = max(family[n], min(1.0, m * p_values[k]))
    return out


def signature_geometry(
    sample: SurfaceSample, jacobian: np.ndarray, sensitivities: np.ndarray, noise: NoiseArg
) -> tuple[np.ndarray, np.ndarray, str]:
    """Retained fractions and cosines of effect signatures in the noise model's metric.

    Parameters
    ----------
    sample : SurfaceSample
    jacobian : ndarray, shape (n,) or (n, p)
    sensitivities : ndarray, shape (n, q)
    noise : NoiseModel or mapping of scan label to NoiseModel

    Returns
    -------
    retained : ndarray, shape (q,)
        ``|P s~_k| / |s~_k|`` with ``s~ = Sigma^{-1/2} s`` and ``P`` the projection off
        ``Sigma^{-1/2} J`` (GLS geometry).
    cosine : ndarray, shape (q, q)
        Cosines between the ``P s~_k``.
    metric : str
        ``"whitened"`` or ``"local-counts"``.
    """
    J = _jacobian(sample, jacobian)
    S = sample.check_values(sensitivities, "sensitivities", columns=True)
    if max(len(b) for b in sample.blocks) <= MAX_DENSE_BLOCK:
        w = whitener(sample, noise)
        Jw, Sw, metric = w.apply(J), w.apply(S), "whitened"
    else:
        sig2 = np.empty(sample.n)
        for label, idx in zip(sample.labels, sample.blocks, strict=True):
            sig2[idx] = _model_for(noise, label).sigma_mm ** 2
        root = np.sqrt(sig2 * local_counts(sample, noise))
        Jw, Sw, metric = J / root[:, None], S / root[:, None], "local-counts"
    coef, *_ = np.linalg.lstsq(Jw, Sw, rcond=None)
    proj = Sw - Jw @ coef
    norm_all = np.linalg.norm(Sw, axis=0)
    norm = np.linalg.norm(proj, axis=0)
    retained = np.where(norm_all > 0, norm / np.where(norm_all > 0, norm_all, 1.0), 0.0)
    unit = proj / np.where(norm > 0, norm, 1.0)
    return retained, unit.T @ unit, metric


def _omegas(sample: SurfaceSample, designs: dict, models: list) -> list[dict]:
    """``C_k' Sigma C_k`` of every design under every model, one covariance pass each."""
    if not designs:
        return [{} for _ in models]
    keys = list(designs)
    cols = [designs[k].columns for k in keys]
    stacked = np.column_stack(cols)
    edges = np.cumsum([0] + [c.shape[1] for c in cols])
    out = []
    for model in models:
        sc = apply_covariance(sample, model, stacked)
        om = {}
        for i, k in enumerate(keys):
            c, s = stacked[:, edges[i] : edges[i + 1]], sc[:, edges[i] : edges[i + 1]]
            o = c.T @ s
            om[k] = 0.5 * (o + o.T)
        out.append(om)
    return out


def screen_effects(
    residual_mm: np.ndarray,
    jacobian: np.ndarray,
    sensitivities: np.ndarray,
    names: Sequence[str],
    sample: SurfaceSample,
    noise: NoiseArg,
    *,
    alpha: float = SCREEN_ALPHA,
    degree: int = 2,
    quantile: Quantile = "imhof",
    min_retained: float = 0.05,
    confounded_above: float = 0.9,
    alternatives: tuple[NoiseArg, ...] = (),
    directions: Sequence[int] | None = None,
    effects: Sequence[str] | None = None,
) -> EffectScreening:
    """Score test of each candidate effect, Holm-corrected, with identifiability.

    Parameters
    ----------
    residual_mm : ndarray, shape (n,)
        Residuals at the fit of ``theta`` (effects at their neutral values).
    jacobian : ndarray, shape (n,) or (n, p)
        ``dr / dtheta`` at the fit.
    sensitivities : ndarray, shape (n, q)
        ``s_k = dr / d beta_k`` of each candidate effect at its neutral value (mm per
        unit of the effect parameter).
    names : sequence of str, length q
    sample : SurfaceSample
    noise : NoiseModel or mapping of scan label to NoiseModel
        Short-range noise model.
    alpha : float
        Family-wise error rate of the significance calls.
    degree : int
        Degree of the series modes (see :func:`calib.stats.intervals.series_design`).
    quantile : {"imhof", "satterthwaite"}
        Exact tail of the ratio or its t approximation.
    min_retained : float
        Effects retaining less of their whitened signature are not identifiable (not
        tested).
    confounded_above : float
        ``|cosine|`` from which two identifiable effects are reported as confounded.
    alternatives : tuple
        Other plausible noise models (the largest p-value is kept).
    directions : sequence of {-1, 0, 1}, optional
        Per effect, the sign a physical departure from neutral can take: +1 (neutral is
        the lower end of the range), -1 (the upper end), 0 (both; the default for all).
        A one-sided effect is tested against that alternative (module docstring).
    effects : sequence of str, optional
        Per column, the effect it belongs to (the family of the Holm correction, module
        docstring); default: every column its own effect.

    Returns
    -------
    EffectScreening

    Raises
    ------
    ScreeningError
        ``names`` not q distinct names, ``alpha`` outside (0, 1), ``directions`` or
        ``effects`` not one valid entry per column, or a residual that the fitted columns
        explain exactly.
    IntervalError
        The Jacobian has rank < p.
    SampleError
        ``residual_mm``, ``jacobian`` or ``sensitivities`` has not one finite row per point
        of ``sample``.
    """
    from scipy import stats

    J = _jacobian(sample, jacobian)
    S = sample.check_values(sensitivities, "sensitivities", columns=True)
    r = sample.check_values(residual_mm, "residual_mm")
    names = tuple(str(n) for n in names)
    if len(names) != S.shape[1] or len(set(names)) != len(names):
        raise ScreeningError(f"need {S.shape[1]} distinct effect names, got {names}")
    if not 0.0 < alpha < 1.0:
        raise ScreeningError(f"alpha must lie in (0, 1), got {alpha}")
    dirs = [0] * len(names) if directions is None else [int(d) for d in directions]
    if len(dirs) != len(names) or not set(dirs) <= {-1, 0, 1}:
        raise ScreeningError(f"need one direction in (-1, 0, 1) per effect, got {directions}")
    groups = names if effects is None else tuple(str(e) for e in effects)
    if len(groups) != len(names):
        raise ScreeningError(f"need one effect per column ({len(names)}), got {len(groups)}")
    _check_not_absorbed(r, J)
    retained, cosine, metric = signature_geometry(sample, J, S, noise)
    ident = retained >= min_retained
    designs = {}
    last = np.eye(J.shape[1] + 1)[-1]
    for k in np.flatnonzero(ident):
        try:
            designs[k] = series_design(
                sample, np.column_stack([J, S[:, k]]), contrast=last, degree=degree
            )
        except IntervalError:
            ident[k] = False
    omegas = _omegas(sample, designs, _models(noise, alternatives))
    rows = []
    for k in range(S.shape[1]):
        if k not in designs:
            rows.append(None)
            continue
        d = designs[k]
        est = float(d.influence @ r)
        best = None
        for m, model in enumerate(_models(noise, alternatives)):
            st = series_statistic(d, r, model, omega=omegas[m][k])
            t = est / st.standard_error
            if quantile == "imhof":
                p = ratio_tail(st.omega, st.weights, abs(t))
            else:
                scale = float(np.sqrt(st.omega[0, 0] / np.sum(st.weights * np.diag(st.omega)[1:])))
                p = float(2.0 * stats.t.sf(abs(t) / scale, st.dof))
            p = one_sided(p, t, dirs[k])
            if best is None or p > best[0]:
                best = (p, t, st)
        rows.append((est, *best))
    adj = _effect_holm([None if row is None else row[1] for row in rows], groups)
    tested = [groups[k] for k in range(len(names)) if rows[k] is not None]
    scores = []
    for k, name in enumerate(names):
        if rows[k] is None:
            scores.append(EffectScore(name, float("nan"), float("nan"), float("nan"), False,
                                       float("nan"), float("nan"), float("nan"), float("inf"),
                                       float(retained[k]), False, float("nan"), 0,
                                       effect=groups[k]))  # fmt: skip
            continue
        est, p, t, st = rows[k]
        # this column's Bonferroni level: alpha over the tested effects (Holm's first
        # step) and over the effect's own tested columns
        level = alpha / (len(set(tested)) * tested.count(groups[k]))
        found = detectable_size(st, level, one_sided=bool(dirs[k]))
        scores.append(EffectScore(name, float(t), float(p), float(adj[k]), bool(adj[k] < alpha),
                                   est, st.standard_error, st.plugin_standard_error,
                                   found, float(retained[k]), True,
                                   st.dof, st.n_modes, ALTERNATIVES[dirs[k]],
                                   groups[k]))  # fmt: skip
    cos = np.where(np.outer(ident, ident), cosine, np.nan)
    pairs = tuple(
        (names[i], names[j], float(cos[i, j]))
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if ident[i] and ident[j] and abs(cos[i, j]) >= confounded_above
    )
    lost = tuple(n for n, ok in zip(names, ident, strict=True) if not ok)
    return EffectScreening(tuple(scores), cos, pairs, lost, alpha, metric, _shown(noise))
