"""Sensitivity fields of the surface residual to every effect of the library.

At converged states of the diagnosis scans (a given ``theta = ln c1`` and effect
values), the derivative of each residual ``r_i`` (a measured point's signed distance
to the simulated surface) to each effect parameter ``p``:

- material effects (skin, inclusions, mooney, poisson) and ``theta``: direct
  sensitivities with the converged tangents (Kleiber et al. 1997, ch. 3). With a
  recovered stress-free reference ``X = x_ref - u0`` (``unload``), first
  ``(K0 - D0) du0/dp = -dR0/dp`` (one factorisation for every parameter), then per scan
  ``K du/dp = -dR/dp - D dX/dp`` (one factorisation per scan for every parameter);
  ``dR/dp`` by central differences of the model at the fixed state
  (:func:`fem.sensitivity.parameter_derivative`; exact for the laws' linear parameters);
- density: at fixed nu the solution depends on ``rho g / c1`` only, so its field is
  ``-dr/dtheta`` exactly (it is reported, not computed: a direct computation agrees to
  solver precision in the tests);
- gravity angles of a scan: ``K du/da = f_ext(dg/da)`` (the load is linear in g), the
  reference posture untouched;
- a rigid offset of a scan: analytic, ``dr = u . (dt + dw x (p - centre))`` with ``u`` the
  unit direction from the simulated surface to the measured point;
- sliding, at a clamped model (the screen): one FE solve per scan and one of the
  reference posture with the plate on stiff tangential springs
  (:attr:`Problem.sliding_probe_pa_per_mm`) at the same c1 and stress-free geometry, the reference
  posture's slip taken off to first order; the field is the secant per unit of the
  probe's amplitude ``a`` (a = 1: springs of the probe's stiffness; for stiff springs the
  slip goes as 1 / k);
- sliding, at a model whose plate is on springs (the refit): the direct sensitivity to
  ``ln k`` like the material effects', ``dR/d ln k = K_s u`` (the springs' own force:
  their matrix is linear in k), through the stress-free recovery too.

The model mesh's dependence (``mesh_error="absorbed"``): not an effect but a nuisance
column like the per-scan offsets: the residual change from the model mesh to one
``f`` = :data:`COARSER_FACTOR` times coarser, at the null fit's c1
(:func:`discretisation_field`), one direction in which the model's answer depends on its
mesh. The tests condition on it (:mod:`calib.discrepancy.screen`), so residual along it
is not counted as evidence of a missing effect, whatever its sign. Where the model mesh's
error goes as ``C h^p`` with one order ``p`` everywhere (the asymptotic range) the change
is that error times ``-(f^p - 1)`` (the premise of grid-refinement estimates, Roache
1998, ch. 5), and the residual carries it with a positive amplitude ``1 / (f^p - 1)``
(:func:`calib.discrepancy.screen.mesh_error_check`, reported). Measured on the
dissertation twins (12 / 16.8 mm against a 5 mm truth) the amplitude is negative (the
coarser mesh fits better along it): the convergence there is not monotone, as the
calibration section found, so the column is a direction of mesh dependence, not an
estimate of the model mesh's error. It is one direction: the clamped edge is a
singularity with a lower order than the bulk, and the two meshes are independent (not
nested).

A vertex-position derivative becomes a residual derivative by the envelope theorem
(the closest point's barycentric weights held fixed, :mod:`calib.model.residuals`).

References
----------
Kleiber, M., Antunez, H., Hien, T. D. & Kowalczyk, P. (1997). *Parameter Sensitivity in
Nonlinear Mechanics*. Wiley.
Roache, P. J. (1998). *Verification and Validation in Computational Science and
Engineering*. Hermosa.
Celik, I. B., Ghia, U., Roache, P. J., Freitas, C. J., Coleman, H. & Raad, P. E. (2008).
Procedure for estimation and reporting of uncertainty due to discretization in CFD
applications. *J. Fluids Eng.* 130(7), 078001.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

import fem
from fem.assemble import external_force
from fem.fields import gravity_vector, vertex_displacement_mm
from fem.linalg import factorize
from fem.sensitivity import geometry_matrix, parameter_derivative, tangent_matrix, vertex_dofs

from ..model.effects import LIBRARY, EffectValues, effect_model, effect_support
from .problem import Problem, gravity_axes

__all__ = [
    "COARSER_FACTOR",
    "DISCRETISATION",
    "MATERIAL_EFFECTS",
    "Column",
    "FieldSet",
    "discretisation_column",
    "discretisation_field",
    "effect_fields",
    "material_dpositions",
]

log = logging.getLogger(__name__)

MATERIAL_EFFECTS = ("skin", "inclusions", "mooney", "poisson")
_EPS = 1e-6  # central-difference step of dR/dp in the parameter's units
#: Name (and effect) of the model mesh's discretisation column.
DISCRETISATION = "discretisation"
#: The discretisation column's second mesh is this many times coarser than the model's
#: (a grid-refinement ratio above 1.3, Celik et al. 2008; coarser, not finer: a finer
#: mesh costs ``f^3`` more and its stress-free recovery fails more often).
COARSER_FACTOR = 1.4


@dataclass(frozen=True)
class Column:
    """One sensitivity column: an effect's parameter (or one of its per-scan parameters).

    Attributes
    ----------
    name : str
        ``effect`` or ``effect[scan].component``.
    effect : str
    scan : str or None
        The scan a per-scan (nuisance) parameter belongs to.
    component : str
    values : dict of str to ndarray
        ``dr/dp`` per scan (mm per parameter unit); zeros where it does not act.
    """

    name: str
    effect: str
    scan: str | None
    component: str
    values: dict


@dataclass(frozen=True)
class FieldSet:
    """Residuals, their derivative in ln c1 and every effect's sensitivity column.

    Attributes
    ----------
    scans : tuple of str
    residual : dict of str to ndarray
    jacobian : dict of str to ndarray
        ``dr/dtheta`` per scan.
    columns : tuple of Column
    unavailable : dict of str to str
        Effects with no field here, and why.
    """

    scans: tuple
    residual: dict
    jacobian: dict
    columns: tuple
    unavailable: dict

    def stack(self, what) -> np.ndarray:
        """Concatenate a per-scan dict over :attr:`scans`."""
        return np.concatenate([what[n] for n in self.scans])

    def matrix(self, names: Sequence[str] | None = None) -> np.ndarray:
        """Columns (by name, default all) stacked over the scans, shape (n, q)."""
        by = {c.name: c for c in self.columns}
        cols = self.columns if names is None else [by[n] for n in names]
        return np.column_stack([self.stack(c.values) for c in cols])


def _param_point(name: str, values: EffectValues) -> float:
    """Where to difference an effect's ``dR/dp``: its value, moved off a lower bound."""
    p = LIBRARY[name].get(values)
    lo = LIBRARY[name].bounds[0]
    return max(p, lo + _EPS) if np.isfinite(lo) else p


def material_dpositions(
    fm,
    theta: float,
    values: EffectValues,
    states: dict,
    names: Sequence[str],
    gravities: dict,
    *,
    gravity_names: Sequence[str] = (),
) -> dict:
    """Vertex-position derivatives of ``theta``, material parameters and gravity angles.

    Parameters
    ----------
    fm : ForwardModel
        After :meth:`~calib.model.forward.ForwardModel.evaluate` at ``(theta, values)``
        (its stress-free geometry and reference state are used).
    theta : float
    values : EffectValues
    states : dict of str to ScanState
        The converged states of ``fm.evaluate``.
    names : sequence of str
        Library effects with a model value (``skin``, ``inclusions``, ``mooney``,
        ``poisson``, ``density``; ``sliding`` when the plate is on springs: ``ln k``).
    gravities : dict of str to ndarray (3,)
        Each scan's gravity direction, as solved.
    gravity_names : sequence of str
        Scans whose two gravity angles are differentiated too.

    Returns
    -------
    dict
        ``{param: {scan: dpositions (n_nodes, 3)}}``, params ``"theta"``, ``names`` and
        ``("gravity", scan, k)``; mm per parameter unit.
    """
    X = fm.stress_free_nodes_mm
    disc = fm.discretization.with_nodes(X)
    c1 = float(np.exp(theta))

    def model_at(name):
        if name == "theta":
            return lambda t: effect_model(disc.mesh, float(np.exp(t)), values)
        eff = LIBRARY[name]
        return lambda p: effect_model(disc.mesh, c1, eff.set(values, p))

    params = ["theta", *names]
    at = {"theta": theta} | {n: _param_point(n, values) for n in names}
    model = effect_model(disc.mesh, c1, values)
    free = disc.free
    v = vertex_dofs(disc)
    dX = {p: np.zeros_like(X) for p in params}
    dX_state = {p: None for p in params}
    unload = fm.reference_state == "unload"

    def dR(p, state, g_vec):
        """``dR/dp`` at a fixed state."""
        if p == "sliding":  # d(k M u)/d ln k: the springs' own force
            return disc.spring @ state
        return parameter_derivative(disc, model_at(p), at[p], state, g_vec)

    if unload:
        u0 = fm.stress_free_state
        if u0 is None:
            raise RuntimeError("no recovered reference state: solve the postures first")
        g0 = gravity_vector(fm.gravity_ref, fm.g_m_s2)
        solve0 = factorize(tangent_matrix(disc, model, u0, shape_load_m_s2=g0))
        for p in params:
            rhs = -dR(p, u0, g0)
            du0 = np.zeros(disc.n_dofs)
            du0[free] = solve0(rhs[free])
            dX[p] = -vertex_displacement_mm(disc, du0)
            dX_state[p] = np.zeros(disc.n_dofs)
            dX_state[p][v] = -du0[v]

    out: dict = {p: {} for p in params}
    for name, st in states.items():
        g_dir, mag = _load(fm, gravities[name])
        g_vec = gravity_vector(g_dir, mag)
        solve = factorize(tangent_matrix(disc, model, st.state))
        D = geometry_matrix(disc, model, st.state, g_vec) if unload else None
        for p in params:
            rhs = -dR(p, st.state, g_vec)[free]
            if dX_state[p] is not None:
                rhs = rhs - D @ dX_state[p][free]
            du = np.zeros(disc.n_dofs)
            du[free] = solve(rhs)
            out[p][name] = dX[p] + vertex_displacement_mm(disc, du)
        if name in gravity_names:
            g_scan = gravity_vector(gravities[name], fm.g_m_s2)
            for k, axis in enumerate(gravity_axes(g_scan)):
                dg = np.cross(axis, g_scan)  # d(R(a) g)/da at a = 0 (the load is linear in g)
                f = external_force(disc, model, dg)
                du = np.zeros(disc.n_dofs)
                du[free] = solve(f[free])
                out.setdefault(("gravity", name, k), {})[name] = vertex_displacement_mm(disc, du)
    return out


def _load(fm, g: np.ndarray) -> tuple[np.ndarray, float]:
    """The load direction and magnitude of a scan's solve (shortcut: ``g - g0``)."""
    if fm.reference_state == "shortcut":
        from fem.unload import shortcut_gravity

        return shortcut_gravity(g, fm.gravity_ref, g_m_s2=fm.g_m_s2)
    return np.asarray(g, float), fm.g_m_s2


def _sliding_secant(prob: Problem, theta: float, values: EffectValues, names: Sequence[str],
                    base: dict, states: dict, nuisance: dict) -> dict:  # fmt: skip
    """Residual change when the plate may slip on stiff tangential springs (per probe).

    The postures are solved with the springs on the stress-free geometry of the clamped
    model, and the slip the springs allow in the reference posture, ``d0 = X + u0 -
    x_ref``, is taken off (to first order the springy model's own stress-free geometry
    is ``X - d0``): one FE solve per scan and one of the reference posture. Under the
    ``shortcut`` reference state ``X`` is the loaded mesh and the reference posture
    carries no load (the solves take ``g - g0``), so there is no slip to take off.
    """
    fm = prob.fm
    X = fm.stress_free_nodes_mm
    # stiff springs (the free plate itself does not converge on calibration meshes)
    probe = replace(values, support_stiffness_pa_per_mm=prob.sliding_probe_pa_per_mm)
    disc = fem.discretize(prob.mesh, effect_support(probe), formulation=fm.formulation)
    disc = disc.with_nodes(X)
    model = effect_model(disc.mesh, float(np.exp(theta)), probe)
    if fm.reference_state == "shortcut":  # X is the loaded mesh, under no load: no slip
        d0, solves = 0.0, 0
    else:
        ref = fem.solve(model, gravity=fm.gravity_ref, g_m_s2=fm.g_m_s2, disc=disc)
        d0, solves = X + ref.displacement_mm - prob.mesh.nodes_mm, 1
    out = {}
    for n in names:
        g, mag = _load(fm, prob.gravity(n, nuisance.get(n)))
        sol = fem.solve(model, gravity=g, g_m_s2=mag, disc=disc, x0=states[n].state)
        pos = X + sol.displacement_mm - d0
        out[n] = prob.residuals(n, pos, None, nuisance.get(n)).r - base[n]
    fm.solves += len(names) + solves
    return out


def discretisation_field(prob: Problem, coarse: Problem, theta: float, residual: dict) -> dict:
    """The residual change from ``prob``'s model mesh to ``coarse``'s, per diagnosis scan.

    Parameters
    ----------
    prob : Problem
    coarse : Problem
        The same work folder on a coarser model mesh (:func:`build_problem` with
        ``mesh_size_mm``); its measured points, centres and noise profile are replaced by
        ``prob``'s, so both residuals are taken at the same points with the same weights.
    theta : float
        ``ln c1`` of both solves (the null fit's).
    residual : dict of str to ndarray (k,)
        ``prob``'s residual at ``theta`` (effects neutral) per diagnosis scan.

    Returns
    -------
    dict of str to ndarray (k,)
        ``r_coarse - r`` (mm) per scan of ``prob.scans``.

    Raises
    ------
    fem.ConvergenceError
        No FE solution (or stress-free recovery) on the coarser mesh.

    Notes
    -----
    The coarser model's FE solves are added to ``prob.fm.solves`` (also where it fails).
    """
    coarse = replace(coarse, points=prob.points, centres=prob.centres, profile=prob.profile)
    try:
        states = coarse.solve(theta, coarse.base, list(prob.scans), gradient=False)
    finally:
        prob.fm.solves += coarse.fm.solves
    return {n: coarse.residuals(n, states[n].positions_mm).r - residual[n] for n in prob.scans}


def discretisation_column(prob: Problem, names: Sequence[str]) -> Column:
    """The column of :attr:`Problem.discretisation` over ``names`` (zeros where it has none)."""
    vals = {n: prob.discretisation.get(n, np.zeros(len(prob.points[n]))) for n in names}
    return Column(DISCRETISATION, DISCRETISATION, None, "amplitude", vals)


def effect_fields(
    prob: Problem,
    theta: float,
    values: EffectValues,
    effects: Sequence[str],
    *,
    names: Sequence[str] | None = None,
    nuisance: dict | None = None,
    say=None,
) -> FieldSet:
    """Residuals and sensitivity columns of the given effects at ``(theta, values)``.

    Parameters
    ----------
    prob : Problem
    theta : float
        ``ln c1``.
    values : EffectValues
    effects : sequence of str
        Library names.
    names : sequence of str, optional
        Scans (default: the diagnosis scans).
    nuisance : dict of str to Nuisance, optional
        Nuisance values per scan (gravity angles, rigid offsets).
    say : callable, optional
        Progress lines.

    Returns
    -------
    FieldSet
    """
    say = say or log.info
    names = list(names or prob.scans)
    unknown = sorted(set(effects) - set(LIBRARY))
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; the library has {sorted(LIBRARY)}")
    nz = nuisance or {}
    states = prob.solve(theta, values, names, gradient=True, nuisance=nz)
    res = {n: prob.residuals(n, states[n].positions_mm, states[n].dpositions_mm, nz.get(n))
           for n in names}  # fmt: skip
    r = {n: res[n].r for n in names}
    J = {n: res[n].dr for n in names}
    unavailable: dict = {}
    mats = [e for e in effects if e in MATERIAL_EFFECTS]
    if "sliding" in effects and values.support == "springs":
        mats.append("sliding")  # the plate on springs: a direct sensitivity to ln k
    if "inclusions" in mats and not prob.inclusions:
        mats.remove("inclusions")
        unavailable["inclusions"] = "no inclusion was detected in the reference scan"
    grav = names if "gravity" in effects else []
    say(f"sensitivities: direct, {len(mats) + 1} parameters x {len(names)} scans")
    gravities = {n: prob.gravity(n, nz.get(n)) for n in names}
    dpos = material_dpositions(prob.fm, theta, values, states, mats, gravities,
                               gravity_names=grav)  # fmt: skip
    cols: list[Column] = []
    zeros = {n: np.zeros_like(r[n]) for n in names}

    def field(dp: dict) -> dict:
        return {n: prob.residuals(n, states[n].positions_mm, dp[n], nz.get(n)).dr
                if n in dp else zeros[n] for n in names}  # fmt: skip

    for e in effects:
        if e in mats:
            cols.append(Column(e, e, None, LIBRARY[e].parameter, field(dpos[e])))
        elif e == "density":
            cols.append(Column(e, e, None, LIBRARY[e].parameter, {n: -J[n] for n in names}))
        elif e == "sliding":
            if values.support != "clamped":  # a free plate: no FE solution on these meshes
                unavailable["sliding"] = f"the model's support is already {values.support}"
                continue
            say(f"sensitivity of sliding: a stiff-spring probe, {len(names) + 1} FE solves")
            try:
                sec = _sliding_secant(prob, theta, values, names, r, states, nz)
            except fem.ConvergenceError as exc:
                unavailable["sliding"] = f"no FE solution with the sliding probe ({exc})"
                continue
            cols.append(Column(e, e, None, "probe_amplitude", sec))
        elif e == "gravity":
            for n in names:
                for k in range(2):
                    vals = zeros | field({n: dpos[("gravity", n, k)][n]})
                    cols.append(Column(f"gravity[{n}].a{k}", e, n, f"a{k}", vals))
        elif e == "registration":
            for n in names:
                pos = states[n].positions_mm
                u = np.column_stack([
                    -prob.residuals(n, pos, np.broadcast_to(np.eye(3)[j], pos.shape), nz.get(n)).dr
                    for j in range(3)
                ])  # fmt: skip
                arm = prob.measured_points(n, nz.get(n)) - prob.centres[n]
                comp = {"tx": u[:, 0], "ty": u[:, 1], "tz": u[:, 2]}
                rot = np.cross(arm, u)  # d r / d w = (p - c) x u
                comp |= {"wx": rot[:, 0], "wy": rot[:, 1], "wz": rot[:, 2]}
                for k, v in comp.items():
                    cols.append(Column(f"registration[{n}].{k}", e, n, k, zeros | {n: v}))
    if prob.discretisation:  # a nuisance every test conditions on (never screened)
        cols.append(discretisation_column(prob, names))
    return FieldSet(tuple(names), r, J, tuple(cols), unavailable)
