"""Noise model, misfit test and score screening of the library's effects on the residuals.

Thin glue over :mod:`calib.stats` (which owns the statistics): the residual field of the
diagnosis scans at the fitted ``ln c1`` is a :class:`calib.stats.SurfaceSample` with one
label per scan; the noise model is a short-range variogram fit of those residuals
(:func:`calib.stats.estimate_noise`, one per scan, with the other plausible kernels as
alternatives) — the session's noise, see below; :func:`calib.stats.misfit_test` asks
whether any large-scale structure is left; :func:`calib.stats.screen_effects` gives each
effect's score test with what ``ln c1`` absorbs projected out, Holm across effects (a
nuisance's per-scan columns are one effect, tested jointly), identifiability and
confounding.

Per-scan offsets: a constant normal offset of a scan's whole measured surface (a
segmentation threshold; the model mesh's faceting, +0.1 mm on the twins' straight facets,
is removed by the curved surface of :mod:`calib.discrepancy.problem`) is no
mechanical effect; one indicator column per scan joins what is projected out, so every
test asks for structure beyond ``ln c1``, the fitted effects and these offsets. The
model mesh's discretisation column (:data:`calib.discrepancy.fields.DISCRETISATION`,
``mesh_error="absorbed"``), where the fields carry one, joins them the same way.

The session's noise. Imaging and the model mesh are the same for every scan of a
session, so the noise process is too; a missing effect only adds to a scan's residual,
and in a short-range variogram it shows as a larger sill and a longer range (a pad
pressing one posture's flank made the pooled fit 0.69 mm over 43 mm, and then nothing
was significant against it). The noise model is therefore the variogram fit of the
least-disturbed scan, the one with the smallest standard deviation, applied to every
scan (:func:`calib.stats.noise.session_noise`). With one scan it is that scan's fit.
Scans imaged unlike (another slice thickness, coil or SNR; ``by_scan``, judged from the
imaging by :attr:`calib.discrepancy.problem.Problem.imaged_unlike`) keep that fit's
correlation at their own short-lag level (:meth:`calib.stats.NoiseFit.scaled`): with one
level for all, a scan three times noisier than the others made its gravity nuisance
significant on null residuals (3 of 16 draws, review W) and left a correct refit short
of explaining half the residual above the quiet scans' floor.
The tests stay ratio statistics (band F, series variances): the model supplies shapes,
the data the scale.

One-sided effects (:attr:`calib.model.effects.Effect.direction`: mooney, poisson, the
sliding probe) are tested against their physical alternative only (a column of an effect
outside the library has no physical range here and is tested two-sided): on the quick null
twin the sliding probe screened significant (t = -4.0) for a plate held *tighter* than
clamped, the model mesh's error at the clamped edge.

Sign: the sensitivity columns of :mod:`calib.discrepancy.fields` are ``dr/dp`` of the
residual ``r`` (measured point minus simulated surface). ``screen_effects``' one-step
estimate ``s~' r / |s~|^2`` is a step in the parameter when ``s`` is the derivative of
the model's prediction, ``-dr/dp``; the columns are passed negated, so every
``estimate`` is the parameter change from neutral that the residual asks for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.effects import LIBRARY
from ..stats import EffectScreening, ModelFit, NoiseFit, SurfaceSample
from ..stats import misfit_test as _misfit_test
from ..stats import screen_effects as _screen_effects
from ..stats.intervals import series_design
from ..stats.noise import MAX_LAG_MM, session_noise
from ..stats.scores import MISFIT_ALPHA, SCREEN_ALPHA, signature_geometry
from .fields import DISCRETISATION, FieldSet

__all__ = [
    "MeshErrorCheck",
    "Screen",
    "influence",
    "mesh_error_check",
    "offset_columns",
    "sample_of",
    "screen",
    "session_noise",
]


@dataclass(frozen=True)
class Screen:
    """Noise model, misfit test and effect screening at one fit.

    Attributes
    ----------
    sample : SurfaceSample
    noise : NoiseFit
        The short-range variogram fit (``best`` and ``plausible``).
    misfit : ModelFit
        Band-F misfit test of the residual.
    screening : EffectScreening or None
        None when no column was screened.
    columns : tuple of str
        Names of the screened columns, in order.
    """

    sample: SurfaceSample
    noise: NoiseFit
    misfit: ModelFit
    screening: EffectScreening | None
    columns: tuple


def offset_columns(sample: SurfaceSample) -> np.ndarray:
    """One indicator column per scan (its constant normal offset), shape (n, scans)."""
    return np.column_stack([(sample.scan == lab).astype(float) for lab in sample.labels])


def _scan_means(sample: SurfaceSample, r: np.ndarray) -> np.ndarray:
    return np.array([r[idx].mean() for idx in sample.blocks])


def sample_of(fields: FieldSet, points: dict) -> SurfaceSample:
    """The residuals' points with one integer label per scan (the order of ``fields.scans``)."""
    pts = np.concatenate([points[n] for n in fields.scans])
    lab = np.concatenate([np.full(len(points[n]), i) for i, n in enumerate(fields.scans)])
    return SurfaceSample(pts, lab)


#: Largest polynomial degree of the series modes of every screened column
#: (:func:`calib.stats.screen_effects`' ``degree``).
SERIES_DEGREE = 2


def _always(fields: FieldSet) -> tuple[str, ...]:
    """Nuisance columns every test conditions on and none screens (the discretisation)."""
    return tuple(c.name for c in fields.columns if c.effect == DISCRETISATION)


def _c1_and_offsets(fields: FieldSet, sample: SurfaceSample) -> np.ndarray:
    """``dr/d ln c1`` and the scans' offset columns, shape (n, 1 + scans)."""
    return np.column_stack([fields.stack(fields.jacobian), offset_columns(sample)])


def _conditioned_on(fields: FieldSet, sample: SurfaceSample, absorbed: tuple = ()) -> np.ndarray:
    """What every test projects out: ``dr/d ln c1``, the scans' offsets, ``absorbed``.

    And the model mesh's discretisation column where the fields have one.
    """
    J = _c1_and_offsets(fields, sample)
    more = (*absorbed, *_always(fields))
    return np.column_stack([J, fields.matrix(more)]) if more else J


def influence(
    fields: FieldSet, points: dict, name: str, *, absorbed: tuple[str, ...] = ()
) -> np.ndarray:
    """The one-step estimate of column ``name`` as a linear map of the residual.

    :func:`screen`'s ``estimate`` of the column is ``influence @ r`` for the stacked
    residual ``r`` (over ``fields.scans``); the vector is orthogonal to ``dr/d ln c1``,
    the per-scan offsets, the ``absorbed`` columns and the discretisation column where the
    fields have one, so what those absorb of a residual never reaches the estimate.

    Parameters
    ----------
    fields : FieldSet
    points : dict of str to ndarray (k, 3)
    name : str
        A column of ``fields``.
    absorbed : tuple of str

    Returns
    -------
    ndarray, shape (n,)
        Parameter units per mm of residual.
    """
    sample = sample_of(fields, points)
    J = _conditioned_on(fields, sample, absorbed)
    design = np.column_stack([J, -fields.matrix([name])])
    last = np.eye(design.shape[1])[-1]
    return series_design(sample, design, contrast=last, degree=SERIES_DEGREE).influence


def screen(
    fields: FieldSet,
    points: dict,
    *,
    columns: tuple[str, ...] | None = None,
    absorbed: tuple[str, ...] = (),
    alpha: float = SCREEN_ALPHA,
    misfit_alpha: float = MISFIT_ALPHA,
    confounded_above: float = 0.9,
    noise: NoiseFit | None = None,
    by_scan: bool = False,
    max_lag_mm: float = MAX_LAG_MM,
) -> Screen:
    """Screen the columns of ``fields`` (default all) at its fit.

    Parameters
    ----------
    fields : FieldSet
        Residuals and columns at the fitted parameters.
    points : dict of str to ndarray (k, 3)
        Where each scan's residuals live.
    columns : tuple of str, optional
        Columns to screen; default every column not in ``absorbed``.
    absorbed : tuple of str
        Columns already fitted (they join ``dr/d ln c1`` in what is projected out).
    alpha : float
        Family-wise error rate of the screening (Holm).
    misfit_alpha : float
        Level of the misfit test (``calib.stats.misfit_test``'s default, 0.01: a model
        mesh's own discretisation leaves some large-scale structure, which a 5 % test
        flags on coarse meshes of a homogeneous twin).
    confounded_above : float
    noise : NoiseFit, optional
        Reuse a noise model (else estimated from this residual).
    by_scan : bool
        The scans are imaged unlike: each gets its own noise level
        (:func:`calib.stats.noise.session_noise`).
    max_lag_mm : float
        The noise model's variogram reaches this far (mm).

    Returns
    -------
    Screen
    """
    sample = sample_of(fields, points)
    r = fields.stack(fields.residual)
    J = _conditioned_on(fields, sample, absorbed)
    r_c = r - offset_columns(sample) @ _scan_means(sample, r)
    if noise is not None and noise.by_scan != by_scan:
        raise ValueError(f"a reused noise model has by_scan={noise.by_scan}, asked {by_scan}")
    fit = noise or session_noise(sample, r_c, by_scan=by_scan, max_lag_mm=max_lag_mm)
    alt = fit.alternatives
    misfit = _misfit_test(r, J, sample, fit.best_arg, alpha=misfit_alpha, alternatives=alt)
    skip = (*absorbed, *_always(fields))
    names = tuple(c.name for c in fields.columns if c.name not in skip) if columns is None \
        else tuple(columns)  # fmt: skip
    if not names:
        return Screen(sample, fit, misfit, None, ())
    S = -fields.matrix(names)  # the prediction's derivative: estimates are parameter steps
    effect = {c.name: c.effect for c in fields.columns}
    directions = [LIBRARY[effect[n]].direction if effect[n] in LIBRARY else 0 for n in names]
    res = _screen_effects(r, J, S, names, sample, fit.best_arg, alpha=alpha, degree=SERIES_DEGREE,
                          confounded_above=confounded_above, alternatives=alt,
                          directions=directions, effects=[effect[n] for n in names])  # fmt: skip
    return Screen(sample, fit, misfit, res, names)


@dataclass(frozen=True)
class MeshErrorCheck:
    """How the residual carries the discretisation column (``mesh_error="absorbed"``).

    Attributes
    ----------
    amplitude : float
        One-step estimate of ``beta`` in ``r ~ beta d`` (``d`` the residual change to the
        coarser mesh), with what ``ln c1`` and the per-scan offsets absorb projected out.
        Where the model mesh's error goes as ``C h^p`` with one order everywhere it is
        ``1 / (f^p - 1)`` (``f`` the coarsening factor; 1.04 for p = 2, 2.5 for p = 1 at
        f = 1.4): positive. Negative: the coarser mesh fits better along ``d`` (a mesh
        dependence that is not monotone).
    standard_error : float
        Its series standard error (:func:`calib.stats.screen_effects`).
    statistic : float
        ``amplitude / standard_error``.
    shared : dict of str to float
        Per screened one-column effect, ``|cos|`` between its signature and the column's,
        both projected off ``ln c1`` and the offsets in the noise model's metric: near 1,
        what the column absorbs of that effect is no longer tested.
    """

    amplitude: float
    standard_error: float
    statistic: float
    shared: dict

    def as_json(self) -> dict:
        """Plain JSON."""
        return {
            "amplitude": float(self.amplitude),
            "standard_error": float(self.standard_error),
            "statistic": float(self.statistic),
            "shared": {k: float(v) for k, v in self.shared.items()},
        }


def mesh_error_check(fields: FieldSet, points: dict, noise: NoiseFit) -> MeshErrorCheck | None:
    """The discretisation column's amplitude in the residual and its overlap with effects.

    Parameters
    ----------
    fields : FieldSet
        At the null fit, with the discretisation column.
    points : dict of str to ndarray (k, 3)
    noise : NoiseFit
        The screen's noise model.

    Returns
    -------
    MeshErrorCheck or None
        None where the fields have no discretisation column.
    """
    names = _always(fields)
    if not names:
        return None
    sample = sample_of(fields, points)
    r = fields.stack(fields.residual)
    J = _c1_and_offsets(fields, sample)
    d = fields.matrix(names)
    alt = noise.alternatives
    est = _screen_effects(
        r, J, d, names, sample, noise.best_arg, degree=SERIES_DEGREE, alternatives=alt
    ).effects[0]
    others = [c.name for c in fields.columns if c.scan is None and c.effect != DISCRETISATION]
    shared = {}
    if others:
        S = np.column_stack([fields.matrix(others), d])
        _, cosine, _ = signature_geometry(sample, J, S, noise.best_arg)
        shared = {n: abs(float(cosine[i, -1])) for i, n in enumerate(others)}
    return MeshErrorCheck(est.estimate, est.standard_error, est.statistic, shared)
