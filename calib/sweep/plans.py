"""Sweep plans: which gravity directions and c1 values a sweep solves.

A plan is a list of scenarios, each a unit gravity direction in the *phantom frame* of
posture angles (:func:`calib.fitting.result.phantom_frame`, :mod:`fem.postures`) and a
c1. Plans:

``dissertation``
    Our reading of the dissertation (chapter 4.4-4.5): training directions every 15 deg
    from 0 to 345 deg in the transverse (x-z) *and* the sagittal (y-z) plane, and 48
    validation directions 10 deg past each training angle (10, 25, ..., 355 deg) in both
    planes. The text says the validation set is "10 deg apart from those in the training
    set" and "includes both the transverse and sagittal planes"; a sagittal direction at
    10 deg is 80 deg away from every transverse direction, so the training set must hold
    sagittal directions as well. The two planes share 90 deg (prone) and 270 deg
    (supine), so 46 distinct training directions + 48 validation = 94 scenarios.
``dissertation:transverse``
    The other reading (24 transverse training directions + the same 48 validation = 72
    scenarios): the sagittal validation directions are then an extrapolation off the
    training plane.
``sphere:N``
    ``N`` quasi-uniform directions over the whole sphere (a Fibonacci lattice,
    :func:`fem.postures.fibonacci_sphere`), all for training unless a seeded fraction is
    held out for validation (``holdout``).

A c1 axis ``LO:HI:N`` (``N`` values spaced geometrically from LO to HI Pa, since c1 is a
scale) multiplies every direction; without it each direction is solved at the calibrated
c1. At a fixed Poisson ratio the strain energy is ``c1`` times a function of the
deformation alone (``W = c1 (I1bar - 3) + kappa/2 (J - 1)^2`` with ``kappa`` proportional
to c1), so equilibrium ``div P + rho g = 0`` depends on ``rho g / c1`` only: the engine
solves every c1 at the calibrated one with gravity scaled by ``c1_cal / c1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fem.postures import fibonacci_sphere, gravity_for_angle

__all__ = [
    "PLANES",
    "ROLES",
    "Plan",
    "PlanError",
    "canonical_c1_axis",
    "make_plan",
    "parse_c1_axis",
]

#: Integer codes of the scenario roles and planes in the store.
ROLES = ("train", "validation")
PLANES = ("transverse", "sagittal", "sphere")
#: The most scenarios one plan holds: its continuation tour is planned in one process,
#: in a time growing faster than N^2 (review AT: seconds at this size)
MAX_SCENARIOS = 20_000
_WHY_MAX = "the continuation tour is planned in one process; split the sweep"


class PlanError(ValueError):
    """A plan or c1 axis that cannot be built (the option and the reason)."""


@dataclass(frozen=True)
class Plan:
    """The scenarios of a sweep, in plan order (directions outer, c1 inner).

    Attributes
    ----------
    spec : str
        The plan as given (``dissertation``, ``sphere:200``, ...).
    gravity_phantom : ndarray, shape (S, 3)
        Unit gravity directions, phantom frame.
    c1_pa : ndarray, shape (S,)
    role : ndarray of int, shape (S,)
        Index into :data:`ROLES`.
    plane : ndarray of int, shape (S,)
        Index into :data:`PLANES`.
    angle_deg : ndarray, shape (S,)
        Posture angle in its plane (NaN for sphere directions).
    c1_axis : str or None
    holdout : float
    seed : int
    """

    spec: str
    gravity_phantom: np.ndarray
    c1_pa: np.ndarray
    role: np.ndarray
    plane: np.ndarray
    angle_deg: np.ndarray
    c1_axis: str | None = None
    holdout: float = 0.0
    seed: int = 0

    def __len__(self) -> int:
        return len(self.c1_pa)

    def describe(self) -> dict:
        """The plan's parameters (what identifies it in a store)."""
        return {
            "spec": self.spec,
            "c1_axis": self.c1_axis,
            "holdout": self.holdout,
            "seed": self.seed,
            "n_scenarios": len(self),
            "n_train": int(np.sum(self.role == 0)),
            "n_validation": int(np.sum(self.role == 1)),
        }


def canonical_c1_axis(text: str | None) -> str | None:
    """``LO:HI:N`` with its numbers written one way (``3e2:6e2:3`` is ``300:600:3``).

    A plan is identified by its description, so that one axis written two ways was
    "another plan" on resume (review AM). Numbers keep every digit (a shorter form could
    give two axes one name).
    """
    if text is None:
        return None
    lo, hi, n = text.split(":")
    lo, hi = (np.format_float_positional(float(v), trim="-") for v in (lo, hi))
    return f"{lo}:{hi}:{int(n)}"


def parse_c1_axis(text: str | None, c1_cal_pa: float) -> np.ndarray:
    """The c1 values of ``--c1 LO:HI:N`` (geometric spacing), or the calibrated c1 alone.

    Parameters
    ----------
    text : str or None
        ``"LO:HI:N"`` in Pa, ``LO <= HI``, ``N >= 1`` (``N = 1`` if and only if ``LO == HI``).
    c1_cal_pa : float
        The calibrated c1 (Pa), used when ``text`` is None.

    Returns
    -------
    ndarray, shape (N,)
        c1 values, Pa, increasing (one value when ``text`` is None).

    Raises
    ------
    PlanError
        ``text`` is not ``LO:HI:N``, ``LO``/``HI`` not finite with ``0 < LO <= HI``,
        ``N < 1``, ``N`` and ``LO == HI`` disagree, or ``N`` exceeds
        :data:`MAX_SCENARIOS`.
    """
    if text is None:
        return np.array([float(c1_cal_pa)])
    parts = text.split(":")
    try:
        lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
        if len(parts) != 3:
            raise ValueError
    except (ValueError, IndexError):
        raise PlanError(f"c1_axis (--c1) must be LO:HI:N (Pa, Pa, count), got {text!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi) or n < 1:
        raise PlanError(f"c1_axis (--c1) {text!r}: need 0 < LO <= HI and N >= 1")
    if n == 1 and lo != hi:
        raise PlanError(f"c1_axis (--c1) {text!r}: one value needs LO == HI")
    if n > 1 and lo == hi:  # review AD: each direction swept N times over (duplicates)
        raise PlanError(f"c1_axis (--c1) {text!r}: LO == HI repeats one c1 {n} times; give N = 1")
    if n > MAX_SCENARIOS:
        raise PlanError(f"c1_axis (--c1) {text!r}: at most {MAX_SCENARIOS} values ({_WHY_MAX})")
    return np.geomspace(lo, hi, n)


def _in_plane(angles, plane: str):
    return np.array([gravity_for_angle(a, plane=plane) for a in angles])


def _dissertation(transverse_only: bool):
    train_t = np.arange(0.0, 360.0, 15.0)
    valid = np.arange(10.0, 360.0, 15.0)
    dirs, role, plane, angle = [], [], [], []

    def add(angles, pl: str, r: int) -> None:
        dirs.append(_in_plane(angles, pl))
        role.extend([r] * len(angles))
        plane.extend([PLANES.index(pl)] * len(angles))
        angle.extend(angles)

    add(train_t, "transverse", 0)
    if not transverse_only:  # 90 and 270 deg are the transverse plane's (prone, supine)
        add(train_t[(train_t != 90.0) & (train_t != 270.0)], "sagittal", 0)
    add(valid, "transverse", 1)
    add(valid, "sagittal", 1)
    return np.vstack(dirs), np.array(role), np.array(plane), np.array(angle, float)


def _sphere(n: int, holdout: float, seed: int):
    dirs = fibonacci_sphere(n)
    role = np.zeros(n, dtype=int)
    k = int(round(holdout * n))
    if holdout > 0 and not 1 <= k <= n - 2:  # review AD: 0.04 of 10 held none out, silently
        raise PlanError(
            f"holdout (--holdout) {holdout:g} of {n} directions holds {k} out: need at least 1 "
            "held out and 2 to train on"
        )
    if k:
        role[np.random.default_rng(seed).choice(n, size=k, replace=False)] = 1
    return dirs, role, np.full(n, PLANES.index("sphere")), np.full(n, np.nan)


def make_plan(
    spec: str,
    *,
    c1_cal_pa: float,
    c1_axis: str | None = None,
    holdout: float = 0.0,
    seed: int = 0,
) -> Plan:
    """Build a plan (see the module docstring for the plans).

    Parameters
    ----------
    spec : str
        ``dissertation``, ``dissertation:transverse`` or ``sphere:N``.
    c1_cal_pa : float
        The calibrated c1, Pa (the c1 of every scenario without a c1 axis).
    c1_axis : str, optional
        ``LO:HI:N`` (:func:`parse_c1_axis`).
    holdout : float
        Fraction of a sphere plan's directions held out for validation (seeded).
    seed : int
        Seed of the held-out choice.

    Returns
    -------
    Plan

    Raises
    ------
    PlanError
        Unknown plan, bad count, or a hold-out on a plan with its own validation set.
    """
    if not 0.0 <= holdout < 1.0:
        raise PlanError(f"holdout (--holdout) must lie in [0, 1), got {holdout}")
    if spec in ("dissertation", "dissertation:transverse"):
        if holdout:
            raise PlanError(
                f"plan (--plan) {spec} has its own validation directions; drop holdout (--holdout)"
            )
        dirs, role, plane, angle = _dissertation(spec.endswith(":transverse"))
    elif spec.startswith("sphere:"):
        try:
            n = int(spec.split(":", 1)[1])
        except ValueError:
            n = 0
        if n < 1:
            raise PlanError(f"plan (--plan) sphere:N needs a positive integer N, got {spec!r}")
        if n > MAX_SCENARIOS:  # review AT: sphere:100000000 planned silently for minutes
            raise PlanError(
                f"plan (--plan) {spec}: at most {MAX_SCENARIOS} directions ({_WHY_MAX})"
            )
        dirs, role, plane, angle = _sphere(n, holdout, seed)
    else:
        raise PlanError(
            f"unknown plan (--plan) {spec!r}; choose dissertation, dissertation:transverse or "
            "sphere:N"
        )
    c1 = parse_c1_axis(c1_axis, c1_cal_pa)
    m = len(c1)
    if len(dirs) * m > MAX_SCENARIOS:
        raise PlanError(
            f"plan (--plan) {spec} with c1_axis (--c1) {c1_axis}: {len(dirs)} directions x {m} "
            f"c1 values is more than {MAX_SCENARIOS} scenarios ({_WHY_MAX})"
        )
    return Plan(
        spec=spec,
        gravity_phantom=np.repeat(dirs, m, axis=0),
        c1_pa=np.tile(c1, len(dirs)),
        role=np.repeat(role, m),
        plane=np.repeat(plane, m),
        angle_deg=np.repeat(angle, m),
        c1_axis=canonical_c1_axis(c1_axis),
        holdout=float(holdout),
        seed=int(seed),
    )
