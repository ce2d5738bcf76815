"""Detectable sizes in the effects' own parameters (``diagnose --parameter-limits``).

The screen's detectable size (:func:`calib.stats.scores.detectable_size`) is in the
units of the one-step estimate: a linearisation at neutral. An effect whose surface
signature saturates needs more of its parameter than that: on the quick twins the
one-step estimate of inclusions five times stiffer than the bulk (excess ratio 4) is
1.3-1.6. This module finds, by the full nonlinear FE model, the parameter value at which
the screen's estimate would reach the detectable size.

The limits are computed at the final model, the one whose screen found nothing more:
the null fit (c1 alone) when nothing was named, else the refit with the named effects
(its screen projects their columns out; a residual that still carried a named skin
would put the other effects' limits where the skin's print is: nu 0.339 on the quick
skin twin at the null fit). Write ``x`` for that fit's parameters (``ln c1`` first,
then the named effects'). Had the scans been made by the model at ``x'`` with the
effect at ``p`` (every other effect as fitted), the fit at ``x`` would leave
``Delta(x', p) = r(x, p0) - r(x', p)`` more in its residual, ``r(x', p)`` the
residuals of that model at the same measured points (``p0`` neutral). The screen's
estimate of the effect is a linear map of the residual, ``e = a' r``
(:func:`calib.discrepancy.screen.influence`), with ``a`` orthogonal to ``J = dr/dx``
(``dr/d ln c1`` and the named effects' columns) and the scans' offsets, so what the fit
absorbs of ``Delta`` to first order never reaches it. An effect with a large c1-like
part does not stop at first order (a skin 8 times stiffer than the bulk passes for a
c1 1.3 times the truth; planted at the null fit's own c1, the skin's estimate turned
negative between ratios of 2.2 and 6 on the quick twins), so ``x'`` holds the
parameters whose planted scans the fit would take for its own ``x``: Gauss-Newton steps
``x' += argmin |J dx - Delta|`` (``J`` at the fit) until a step moves the residual by
less than a c1 step of :data:`C1_TOL` would (``Delta`` orthogonal to ``J``, the fit's
normal equations; with c1 alone, ``t += J' Delta / J' J`` until ``|step| <
C1_TOL``)::

    e(p) = a' Delta(x'(p), p),    e(p) -> p - p0 as p -> p0 (the column is -dr/dp at p0)

The limit is where ``e`` reaches the detectable size ``d`` on the effect's physical side:
stiffer skin and inclusions, c2 > 0, a more compressible material (nu below the
model's), a plate on softer tangential springs. Along that side the distance ``s`` from
neutral is in the screen's units (``s = p - p0``; poisson ``s = nu0 - nu``; sliding the
probe amplitude, ``s = k_probe / k``, the slip of stiff springs going as ``1 / k``). The
search starts at the linearisation ``s = d`` and takes secant steps on ``ln e`` against
``ln s`` (slope 1 at the start), clipped to the physical range; it ends within
``rtol`` of ``d``, at the range's end with ``e`` still short of ``d`` ("beyond the
range"), or where the FE model has no solution. When the first size has none (on the
quick twins the stress-free recovery with the plate on springs stiffer than 1500 Pa/mm
can fail), a size :data:`FAILED_GROWTH` times larger is tried once, and a limit found
from there is an upper bound (``note`` says so).

It costs one FE solve of each diagnosis scan per c1 step (and the effect's stress-free
recovery), one to three c1 steps per size and two to five sizes per effect.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

import fem

from ..model.effects import LIBRARY, EffectValues
from .problem import Problem
from .refit import SLIDING_PROBE_MULTIPLES, Refit, unpack_parameters
from .screen import Screen, influence

__all__ = [
    "LIMITED_EFFECTS",
    "SATURATED_BELOW",
    "ParameterLimit",
    "parameter_limit",
    "parameter_limits",
    "visible_side",
]

log = logging.getLogger(__name__)

#: Gauss-Newton steps of ln c1 below this end the planted model's bulk c1 (0.5 %
#: of c1: ``a`` is orthogonal to ``J``, so the error left is second order in it).
C1_TOL = 0.005
#: Gauss-Newton steps of ln c1 at most per size.
C1_STEPS = 4
#: A size step grows the distance from neutral by this factor at most.
MAX_GROWTH = 4.0
#: When the first size has no FE solution, the next is this much larger (once).
FAILED_GROWTH = 1.5

#: An elasticity ``d ln e / d ln s`` below this at the limit is a saturated print: the
#: size would have to grow 16-fold to double the estimate (stiff inclusions on the quick
#: twins: 0.03-0.5; every other effect 0.8-1.2).
SATURATED_BELOW = 0.25

#: Effects whose limit is searched: the global physical ones with a model parameter.
LIMITED_EFFECTS = ("skin", "inclusions", "mooney", "poisson", "sliding")


@dataclass(frozen=True)
class ParameterLimit:
    """The parameter value whose signature the screen would estimate at its detectable size.

    Attributes
    ----------
    effect : str
    detectable : float
        The screen's detectable size (one-step units, :attr:`steps` ``s``).
    status : {"reached", "beyond the range", "no FE solution", "not settled"}
        ``reached``: ``value`` is the limit: the smallest size solved whose estimate came
        within ``rtol`` of the detectable size or above it (the limit itself, or an upper
        bound of it when the steps ran out); ``beyond the range``: even the physical
        range's end gives less; ``no FE solution``: the search stopped where the model
        could not be solved, short of the size; ``not settled``: the steps ran out short
        of it.
    distance : float or None
        The limit's distance from neutral in one-step units (``s``), None when not reached.
    value : float or None
        The limit in the quantity :attr:`quantity` names, None when not reached.
    quantity : str
        What ``value`` is (``"skin c1 / bulk c1"``, ``"nu"``, ``"springs, Pa/mm"``, ...).
    steps : tuple of (float, float, float)
        ``(s, e(s), c1 ratio)`` of every size solved, in order: the ratio is the planted
        model's bulk c1 over the fit's, the c1 whose planted scans the fit takes for its
        own c1 (below 1 for a stiffer skin).
    note : str
        Why the search stopped short, where it did (the FE failure's message).
    upper_bound : bool
        ``reached`` from above a size with no FE solution: the limit may lie nearer
        neutral than ``value``.
    model : tuple of str
        The effects in the model the limit was computed at, besides c1 (the named ones;
        empty: the null fit).
    """

    effect: str
    detectable: float
    status: Literal["reached", "beyond the range", "no FE solution", "not settled"]
    distance: float | None
    value: float | None
    quantity: str
    steps: tuple = ()
    note: str = ""
    upper_bound: bool = False
    model: tuple = ()

    @property
    def elasticity(self) -> float | None:
        """``d ln e / d ln s`` at the limit (or the largest size tried when not reached).

        The secant through the two sizes nearest it with a positive estimate; None with
        fewer. Near 1 the print grows with the size; below :data:`SATURATED_BELOW` it
        has saturated, and the limit says little more than "barely visible at any size".
        """
        good = [(si, ei) for si, ei, _ in self.steps if ei > 0]
        if len(good) < 2:
            return None
        at = self.distance if self.distance is not None else max(si for si, _ in good)
        near = sorted(good, key=lambda p: abs(math.log(p[0] / at)))[:2]
        (s0, e0), (s1, e1) = sorted(near)
        return math.log(e1 / e0) / math.log(s1 / s0) if s1 != s0 else None

    @property
    def saturated(self) -> bool:
        """The :attr:`elasticity` is below :data:`SATURATED_BELOW`."""
        el = self.elasticity
        return el is not None and el < SATURATED_BELOW

    @property
    def visible(self) -> Literal["above", "below"]:
        """:func:`visible_side` of the effect."""
        return visible_side(self.effect)

    @property
    def linearised_ratio(self) -> float | None:
        """``distance / detectable``: how much more than the linearisation the limit needs."""
        return None if self.distance is None else self.distance / self.detectable

    def as_json(self) -> dict:
        """Plain JSON (``diagnosis.json``'s ``effects.<name>.parameter_limit``)."""
        return {
            "status": self.status,
            "value": self.value,
            "quantity": self.quantity,
            "distance": self.distance,
            "detectable": self.detectable,
            "steps": [[float(v) for v in step] for step in self.steps],
            "note": self.note or None,
            "upper_bound": self.upper_bound,
            "model": list(self.model),
            "elasticity": self.elasticity,
            "saturated": self.saturated,
            "visible": self.visible,
        }


def visible_side(effect: str) -> Literal["above", "below"]:
    """Where the screen would find an effect relative to its limit's value.

    ``"above"``: stiffer skin and inclusions, more c2; ``"below"``: a smaller nu, softer
    springs (the quantity falls as the distance from neutral grows). A truth on the
    other side of the limit lies inside it: these data would not show it.

    Parameters
    ----------
    effect : str
        One of :data:`LIMITED_EFFECTS`.

    Returns
    -------
    {"above", "below"}
    """
    if effect not in LIMITED_EFFECTS:
        raise ValueError(f"no parameter limit for {effect!r}; it is for {LIMITED_EFFECTS}")
    return "below" if _value(effect, 2.0, 0.5, 1.0) < _value(effect, 1.0, 0.5, 1.0) else "above"


def _quantity(effect: str) -> str:
    return {
        "skin": "skin c1 / bulk c1",
        "inclusions": "inclusion c1 / bulk c1",
        "mooney": "c2 / c1",
        "poisson": "nu",
        "sliding": "tangential springs, Pa/mm",
    }[effect]


def _s_max(effect: str, nu0: float) -> float:
    """The physical range's end along the effect's side, in one-step units.

    ``nu0`` is the model's nu (poisson's neutral); sliding's softest springs are the
    refit's lower bound, a fixed fraction of the probe.
    """
    if effect == "poisson":
        return nu0 - LIBRARY["poisson"].bounds[0]
    if effect == "sliding":
        return 1.0 / SLIDING_PROBE_MULTIPLES[0]
    return LIBRARY[effect].bounds[1]


def _value(effect: str, s: float, nu0: float, probe_pa_per_mm: float | None) -> float:
    """The quantity :func:`_quantity` names at distance ``s`` from neutral."""
    if effect in ("skin", "inclusions"):
        return 1.0 + s
    if effect == "poisson":
        return nu0 - s
    if effect == "sliding":
        return probe_pa_per_mm / s
    return s


def _values_at(
    effect: str, base: EffectValues, s: float, probe_pa_per_mm: float | None
) -> EffectValues:
    """``base`` with the effect at distance ``s`` from neutral on its physical side."""
    lib = LIBRARY[effect]
    if effect == "poisson":
        return lib.set(base, base.nu - s)
    if effect == "sliding":
        return lib.set(base, math.log(probe_pa_per_mm / s))
    return lib.set(base, s)


def parameter_limit(
    prob: Problem,
    fit: Refit,
    scr: Screen,
    effect: str,
    *,
    absorbed: tuple[str, ...] = (),
    rtol: float = 0.05,
    max_steps: int = 8,
    say: Callable[[str], None] | None = None,
) -> ParameterLimit:
    """The limit of one effect (see the module docstring).

    Parameters
    ----------
    prob : Problem
    fit : Refit
        The fit the screen ``scr`` was made at: the null fit (c1 alone) or a refit with
        named effects (their values stay in the planted model, their parameters join
        c1 in the Gauss-Newton steps).
    scr : Screen
        The fit's screen; its column ``effect`` gives the detectable size.
    effect : str
        One of :data:`LIMITED_EFFECTS`, not among ``fit.effects``.
    absorbed : tuple of str
        The columns ``scr`` projected out besides c1 (the named effects'; ``screen``'s
        ``absorbed``).
    rtol : float
        Relative tolerance on reaching the detectable size.
    max_steps : int
        Sizes tried at most (each one to :data:`C1_STEPS` FE solves of every scan).
    say : callable, optional
        Progress lines.

    Returns
    -------
    ParameterLimit

    Raises
    ------
    ValueError
        An effect outside :data:`LIMITED_EFFECTS` or in the fit, or one the screen did
        not test (no column, not identifiable, or no finite detectable size).
    """
    say = say or log.info
    if effect not in LIMITED_EFFECTS:
        raise ValueError(f"no parameter limit for {effect!r}; it is for {LIMITED_EFFECTS}")
    if effect in fit.effects:
        raise ValueError(f"{effect!r} is in the fit already (its effects: {fit.effects})")
    rows = [e for e in (scr.screening.effects if scr.screening else ()) if e.name == effect]
    if not rows or not rows[0].identifiable or not np.isfinite(rows[0].detectable):
        raise ValueError(f"the screen has no tested column {effect!r} with a detectable size")
    d = float(rows[0].detectable)
    sign = -1.0 if LIBRARY[effect].direction < 0 else 1.0  # poisson: the estimate is -s
    a = influence(fit.fields, prob.points, effect, absorbed=absorbed)
    base_r = fit.fields.stack(fit.fields.residual)
    names = list(fit.fields.scans)
    nu0 = fit.values.nu
    probe = prob.sliding_probe_pa_per_mm if effect == "sliding" else None
    s_max = _s_max(effect, nu0)
    quantity = _quantity(effect)

    J = fit.jacobian()  # (n, len(x)): dr/d ln c1 first
    small = C1_TOL * float(np.linalg.norm(J[:, 0]))  # what a c1 step of C1_TOL moves
    x_of: dict[float, np.ndarray] = {}  # the x' found at each size: the next starts there

    def estimate(s: float) -> tuple[float, float]:
        near = min(x_of, key=lambda k: abs(math.log(k / s)), default=None)
        x = np.array(fit.x, float) if near is None else x_of[near].copy()
        for _ in range(C1_STEPS):
            x_solved = x
            theta, values, nz = unpack_parameters(prob, fit.names, x, fit.values)
            values = _values_at(effect, values, s, probe)
            states = prob.solve(theta, values, names, gradient=False, nuisance=nz)
            res = [prob.residuals(n, states[n].positions_mm, None, nz.get(n)).r for n in names]
            delta = base_r - np.concatenate(res)
            step = np.linalg.lstsq(J, delta, rcond=None)[0]
            if float(np.linalg.norm(J @ step)) < small:
                break
            # the named effects stay in their physical range; c1 is free (the refit's
            # bounds on it are a search range about the calibration's)
            x = x + step
            x[1:] = np.clip(x[1:], fit.lower[1:], fit.upper[1:])
        x_of[s] = x
        # the estimate and the c1 ratio of the last model solved (x moved on when the
        # steps ran out)
        return sign * float(a @ delta), float(np.exp(x_solved[0] - fit.theta))

    steps: list[tuple[float, float, float]] = []
    note, failed_at = "", 0.0
    s, slope = min(d, s_max), 1.0
    status: str = "beyond the range"
    for _ in range(max_steps):
        try:
            e, c1_ratio = estimate(s)
        except fem.ConvergenceError as exc:
            note = f"no FE solution at {quantity} {_value(effect, s, nu0, probe):.4g} ({exc})"
            say(f"  {effect}: {note}")
            status = "no FE solution"
            if steps or s >= s_max or failed_at:
                break
            # the first size has none (a stiff plate's recovery on springs): once, a
            # larger one; a limit found above it is then an upper bound of the limit
            failed_at, s = s, min(FAILED_GROWTH * s, s_max)
            continue
        steps.append((s, e, c1_ratio))
        at = _value(effect, s, nu0, probe)
        c1 = f"planted bulk c1 x{c1_ratio:.3f} of the fit's"
        say(f"  {effect} at {quantity} {at:.4g}: estimate {e:.3g} (detectable {d:.3g}), {c1}")
        if e > 0 and abs(e / d - 1.0) <= rtol:
            status = "reached"
            break
        if s >= s_max and e < d:
            break
        good = [(si, ei) for si, ei, _ in steps if ei > 0]
        if len(good) >= 2:
            (s0, e0), (s1, e1) = good[-2], good[-1]
            if s1 != s0 and e1 != e0:
                slope = max(math.log(e1 / e0) / math.log(s1 / s0), 0.05)
        s_next = s * 2.0 if e <= 0 else s * (d / e) ** (1.0 / slope)
        s_next = min(s_next, MAX_GROWTH * s)  # a flat secant must not leap to the range's end
        below = [si for si, ei, _ in steps if ei < d]
        above = [si for si, ei, _ in steps if ei >= d]
        lo, hi = max([*below, failed_at], default=0.0), min(above, default=math.inf)
        if not lo < s_next < hi:  # keep the bracket: bisect in ln s
            s_next = math.sqrt(lo * hi) if lo > 0 and math.isfinite(hi) else s_next
        s = min(s_next, s_max)
    prob.fm.set_effects(prob.base)
    model = tuple(fit.effects)
    # the smallest size solved whose estimate reached d (within rtol): at the tolerance
    # when the search settled, else an upper bound of the limit
    reached = [si for si, ei, _ in steps if ei >= d * (1.0 - rtol)]
    if reached:
        s = min(reached)
        value = _value(effect, s, nu0, probe)
        if failed_at:
            note += "; the limit found above it is an upper bound"
        return ParameterLimit(
            effect, d, "reached", s, value, quantity, tuple(steps), note, bool(failed_at), model
        )
    if status != "no FE solution" and not (steps and steps[-1][0] >= s_max):
        status = "not settled"
    return ParameterLimit(effect, d, status, None, None, quantity, tuple(steps), note, model=model)


def parameter_limits(
    prob: Problem,
    fit: Refit,
    scr: Screen,
    effects,
    *,
    absorbed: tuple[str, ...] = (),
    rtol: float = 0.05,
    say: Callable[[str], None] | None = None,
) -> dict[str, ParameterLimit]:
    """:func:`parameter_limit` of each of ``effects`` the screen tested and did not find.

    Effects outside :data:`LIMITED_EFFECTS`, in the fit, not tested (unavailable, not
    identifiable) or significant are left out. ``fit``, ``scr`` and ``absorbed`` as for
    :func:`parameter_limit`.
    """
    say = say or log.info
    rows = {e.name: e for e in (scr.screening.effects if scr.screening else ())}
    out = {}
    for eff in effects:
        row = rows.get(eff)
        if eff not in LIMITED_EFFECTS or eff in fit.effects or row is None:
            continue
        if not row.identifiable or row.significant:
            continue
        if not np.isfinite(row.detectable):
            continue
        say(f"parameter limit of {eff}: the size whose estimate reaches {row.detectable:.3g}")
        out[eff] = parameter_limit(prob, fit, scr, eff, absorbed=absorbed, rtol=rtol, say=say)
    return out
