"""Newton-Raphson with line search and adaptive load stepping."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .assemble import assemble, external_force, scatter
from .discretize import Discretization, Formulation, discretize
from .fields import _point_forces, displacement_at, gravity_vector, vertex_displacement_mm
from .linalg import LinearSolver, factorize, solve_preconditioned
from .model import Model, as_supports
from .units import M_PER_MM, MM_PER_M, STANDARD_GRAVITY_M_S2

__all__ = [
    "ConvergenceError",
    "Solution",
    "SolverOptions",
    "displacement_at",
    "gravity_vector",
    "solve",
    "vertex_displacement_mm",
]


class ConvergenceError(RuntimeError):
    """The load could not be applied: Newton failed even at the smallest load step.

    Attributes
    ----------
    element : int or None
        The element that lost the most volume at the last converged state (the one
        :func:`stall_note` names), where the solve knows it; None otherwise.
    """

    # a default, so that a process pool's worker can pickle it (the attribute travels in
    # the exception's __dict__)
    def __init__(self, *args, element: int | None = None):
        super().__init__(*args)
        self.element = element


@dataclass(frozen=True)
class SolverOptions:
    """Controls of the nonlinear solve.

    Attributes
    ----------
    rtol : float
        Convergence when the free residual force is below ``rtol`` times the norm of
        the full external load (and the pressure residual below ``rtol`` times the
        body volume for mixed formulations).
    max_newton : int
        Newton iterations per load step before the step is cut back.
    initial_step, min_step : float
        First and smallest load-factor increments.
    max_steps : int
        Most load steps (successful or not) in one solve.
    line_search : bool
        Backtracking on the residual norm.
    linear_solver : {"auto", "pardiso", "superlu"}
    reuse_factor_below : float
        Below this scaled residual a Newton step first tries the previous tangent's
        factorization as a GMRES preconditioner (a few back-substitutions instead of a
        new factorization) and factorises only when that does not reach the step
        accuracy; 0 always factorises.
    """

    rtol: float = 1e-8
    max_newton: int = 12
    initial_step: float = 1.0
    min_step: float = 1.0 / 1024
    max_steps: int = 200
    line_search: bool = True
    linear_solver: LinearSolver = "auto"
    reuse_factor_below: float = 1e-2


@dataclass(frozen=True)
class Solution:
    """Result of one static solve.

    Attributes
    ----------
    displacement_mm : ndarray, shape (n_nodes, 3)
        Displacement of the mesh vertices, model frame, mm.
    state : ndarray, shape (n_dofs,)
        Full solver vector (solver frame, SI); pass as ``x0`` to warm-start.
    converged : bool
    newton_iterations : int
        Total over all load steps, including failed ones.
    load_steps : int
        Successful load increments.
    cutbacks : int
        Failed increments that were retried with a smaller step.
    residual_history : tuple of float
        Relative residual after every Newton iteration.
    timings_s : dict
        ``assembly``, ``linear_solve`` and ``total`` wall times in s.
    dofs : int
        Free unknowns of the linear systems.
    formulation : str
    factorizations : int
        Sparse factorizations; Newton steps beyond these reused an earlier one.
    """

    displacement_mm: np.ndarray
    state: np.ndarray
    converged: bool
    newton_iterations: int
    load_steps: int
    cutbacks: int
    residual_history: tuple[float, ...]
    timings_s: dict = field(default_factory=dict)
    dofs: int = 0
    formulation: str = ""
    factorizations: int = 0

    @property
    def max_displacement_mm(self) -> float:
        """Largest vertex displacement magnitude in mm."""
        return float(np.linalg.norm(self.displacement_mm, axis=1).max())


@dataclass
class _Stats:
    newton: int = 0
    history: list = field(default_factory=list)
    first_step_m: float = 0.0  # the largest displacement of a load step's first Newton step
    t_asm: float = 0.0
    t_lin: float = 0.0
    factorizations: int = 0


def merit(r_free, u_free, f_scale: float, v_scale: float, mixed: bool) -> float:
    """Scaled residual norm: force part over the load norm, pressure part over the volume."""
    ru = np.linalg.norm(r_free[u_free]) / f_scale
    rp = np.linalg.norm(r_free[~u_free]) / v_scale if mixed else 0.0
    return float(np.hypot(ru, rp))


def merit_weights(u_free, f_scale: float, v_scale: float) -> np.ndarray:
    """Row weights ``D`` with ``merit = |D r|`` (force rows over the load, others over volume)."""
    return np.where(u_free, 1.0 / f_scale, 1.0 / max(v_scale, 1e-300))


class _Problem:
    """One load case on one discretization: residual, tangent and norms."""

    def __init__(self, disc: Discretization, model: Model, f_ext: np.ndarray, opts, stats):
        self.disc, self.model, self.f_ext, self.opts, self.stats = disc, model, f_ext, opts, stats
        self.free = disc.free
        nu = 3 * disc.n_scalar_u
        self.u_free = self.free < nu
        self.f_scale = max(np.linalg.norm(f_ext), 1e-300)
        self.v_scale = float(disc.weights.sum())
        if disc.spring is not None:
            self.spring_ff = disc.spring[self.free][:, self.free].tocsr()
        self.factor = None

    def residual(self, x, lam, tangent):
        t0 = time.perf_counter()
        st = assemble(self.disc, self.model, x, tangent=tangent)
        if st.min_J <= 0:
            self.stats.t_asm += time.perf_counter() - t0
            return None, None
        r = scatter(self.disc, st.vectors) - lam * self.f_ext
        if self.disc.spring is not None:
            r += self.disc.spring @ x
        K = None
        if tangent:
            K = self.disc.pattern.matrix(st.matrices)
            if self.disc.spring is not None:
                K = K + self.spring_ff
        self.stats.t_asm += time.perf_counter() - t0
        return r[self.free], K

    @property
    def scale(self) -> np.ndarray:
        """Row weights of the free residual whose norm is :meth:`merit`."""
        return merit_weights(self.u_free, self.f_scale, self.v_scale)

    def merit(self, r_free) -> float:
        return merit(r_free, self.u_free, self.f_scale, self.v_scale, self.disc.mixed)

    def linear_solve(self, K, r, m: float):
        """Newton step ``K dx = -r`` (the tangent is symmetric: conservative loads)."""
        return newton_step(self, K, r, m, symmetric=True)


def newton_step(prob, K, r, m: float, *, symmetric: bool) -> np.ndarray:
    """Solve ``K dx = -r``; late steps reuse ``prob.factor``, an earlier factorization.

    Below ``opts.reuse_factor_below`` the step is first sought by GMRES preconditioned
    with the previous factorization, to a scaled linear residual ``min(1e-3, m)`` times
    the merit ``m`` (an inexact Newton step that keeps the quadratic rate); when that is
    not reached in a few back-substitutions, ``K`` is factorised.
    """
    t0 = time.perf_counter()
    dx = None
    if prob.factor is not None and m < prob.opts.reuse_factor_below:
        dx = solve_preconditioned(K, -r, prob.factor, scale=prob.scale, rtol=min(1e-3, m))
    if dx is None:
        method = prob.opts.linear_solver
        prob.factor = factorize(K, method=method, symmetric=symmetric)
        prob.stats.factorizations += 1
        dx = prob.factor(-r)
    prob.stats.t_lin += time.perf_counter() - t0
    return dx


def _line_search(prob: _Problem, x, dx_free, lam, m0):
    """Backtrack until the residual norm decreases; returns (x, r, K, merit) or None.

    In Newton's region the full step is evaluated with its tangent (the usual, accepted
    case); far from it (often backtracked) or where it is expected to converge, and
    for every shorter trial step, the residual alone is checked first. The tangent of
    an accepted point is assembled only when another Newton step needs it (``K`` is
    None for a converged point).
    """
    alpha, rtol = 1.0, prob.opts.rtol
    # the tangent goes with the full step where that step is expected to be accepted
    # (m0 small, Newton's region) and not to be the last (m0^2 well above rtol)
    full_with_tangent = 10.0 * np.sqrt(rtol) < m0 < 0.1 or not prob.opts.line_search
    for k in range(6 if prob.opts.line_search else 1):
        xt = x.copy()
        xt[prob.free] += alpha * dx_free
        r, K = prob.residual(xt, lam, tangent=k == 0 and full_with_tangent)
        if r is not None:
            m = prob.merit(r)
            if np.isfinite(m) and (m < m0 or not prob.opts.line_search or alpha < 0.05):
                if K is None and m > rtol:
                    r, K = prob.residual(xt, lam, tangent=True)
                return xt, r, K, m
        alpha *= 0.5
    return None


def _newton(prob: _Problem, x, lam):
    """Newton iterations at load factor ``lam``; returns the converged x or None."""
    r, K = prob.residual(x, lam, tangent=False)
    if r is None:
        return None
    m = prob.merit(r)
    if m > prob.opts.rtol:
        r, K = prob.residual(x, lam, tangent=True)
    for k in range(prob.opts.max_newton):
        if m <= prob.opts.rtol:
            return x
        dx = prob.linear_solve(K, r, m)
        prob.stats.newton += 1
        if k == 0 and np.any(prob.u_free):  # the step's linear response: the load's size
            moved = float(np.max(np.abs(dx[prob.u_free])))
            prob.stats.first_step_m = max(prob.stats.first_step_m, moved)
        step = _line_search(prob, x, dx, lam, m)
        if step is None:
            return None
        x, r, K, m_new = step
        prob.stats.history.append(m_new)
        if not np.isfinite(m_new) or m_new > 1e6 * max(m, prob.opts.rtol):
            return None
        m = m_new
    return x if m <= prob.opts.rtol else None


def _apply_dirichlet(x, prescribed, lam):
    if prescribed is not None:
        x = x.copy()
        x[prescribed[0]] = lam * prescribed[1]
    return x


def _failure_cause(stats: _Stats, lam: float, rtol: float, extent_mm: float) -> str:
    """Why a load stepping failed, in words: a load too large, or one too small to resolve.

    Where no step converged and no load step's first Newton step (its linear response)
    moved a node by a millionth of the body's extent, the load is tiny against the
    stiffness: the internal force's rounding error (relative to the stiffness) exceeds
    ``rtol`` times the load, and the residual stalls at roundoff (a 40 mm cube at 420 Pa
    under 1e-7 m/s^2 moves 1.7e-7 mm, 4e-9 of its size; review AY: a residual cutoff
    missed loads far under the tolerance).
    """
    moved = stats.first_step_m * MM_PER_M
    if lam <= 0.0 and moved < 1e-6 * extent_mm:
        return (
            f"the load moves the body by about {moved:.1e} mm (Newton's first, linear step), "
            f"under a millionth of its {extent_mm:.3g} mm: too small against the material's "
            f"stiffness for the residual to fall under the tolerance ({rtol:g} of the load) "
            "at roundoff (a negligible gravity or a very stiff material)"
        )
    return (
        "the load may be too large for the material (elements invert) or the support "
        "leaves the body free"
    )


def stall_note(
    disc: Discretization, model: Model, x: np.ndarray, lam: float, *, load: str = "the load"
) -> str:
    """Where a failed load stepping stopped, for its error message.

    The load factor reached and, at the last converged state ``x``, the vertex
    tetrahedron (the straight element through the vertices) that lost the most volume:
    whether it turned inside out and how far it lies from the support's nodes. A body
    that fails at its clamped rim (a thin wedge of material pressed onto the back) and
    one that fails in its bulk read differently.

    Parameters
    ----------
    disc : Discretization
    model : Model
        On ``disc.mesh``.
    x : ndarray, shape (n_dofs,)
        The last converged state (displacement from ``disc.mesh``).
    lam : float
        Its load factor, in [0, 1).
    load : str
        What ``lam`` is a share of, in words.

    Returns
    -------
    str
    """
    return _stall(disc, model, x, lam, load)[0]


def _stall(disc: Discretization, model: Model, x: np.ndarray, lam: float, load: str):
    """:func:`stall_note`'s text and its element (None where no step converged)."""
    if lam <= 0.0:
        return f"no step of {load} converged", None
    mesh = disc.mesh
    moved = mesh.with_nodes(mesh.nodes_mm + vertex_displacement_mm(disc, x))
    ratio = moved.volumes_mm3() / mesh.volumes_mm3()
    e = int(np.argmin(ratio))
    held = np.unique(
        np.concatenate([mesh.node_set(s.node_set) for s in as_supports(model.support)])
    )
    d_mm = np.linalg.norm(
        mesh.nodes_mm[mesh.tets[e]][:, None] - mesh.nodes_mm[held][None], axis=2
    ).min()
    r, n_inv = float(ratio[e]), int((ratio <= 0).sum())
    state = (
        f"had turned inside out (volume ratio {r:.2f}; {n_inv} inverted)"
        if r <= 0
        else f"kept {r:.0%} of its volume"
    )
    return (
        f"it reached {lam:.1%} of {load}; there the most squeezed vertex tetrahedron "
        f"(element {e}, {d_mm:.1f} mm from the support's nodes) {state}"
    ), e


def _load_steps(prob: _Problem, x, prescribed, opts: SolverOptions):
    """Adaptive load stepping from ``lam = 0`` to 1; returns (x, lam, steps, cutbacks, ok)."""
    lam, dlam, steps, cuts = 0.0, opts.initial_step, 0, 0
    x_prev, dlam_prev = None, opts.initial_step
    for _ in range(opts.max_steps):
        trial = min(1.0, lam + dlam)
        guess = _apply_dirichlet(x, prescribed, trial)
        if x_prev is not None and steps > 0:
            pred = guess + (trial - lam) / dlam_prev * (x - x_prev)
            guess = _apply_dirichlet(pred, prescribed, trial)
        n0 = prob.stats.newton
        x_new = _newton(prob, guess, trial)
        if x_new is None and x_prev is not None:
            x_new = _newton(prob, _apply_dirichlet(x, prescribed, trial), trial)
        if x_new is None:
            cuts += 1
            dlam *= 0.25
            if dlam < opts.min_step:
                return x, lam, steps, cuts, False
            continue
        x_prev, dlam_prev, x, lam, steps = x, trial - lam, x_new, trial, steps + 1
        if lam >= 1.0:
            return x, lam, steps, cuts, True
        iters = prob.stats.newton - n0
        dlam = min(dlam * (2.0 if iters <= 5 else 1.0), 1.0 - lam)
    return x, lam, steps, cuts, False


def _prescribed_dofs(disc: Discretization, prescribed: dict | None):
    """``{(node_set, component): value_mm}`` to solver-frame full-vector dofs and values (m)."""
    if not prescribed:
        return None
    if not np.allclose(disc.R_solver_from_model, np.eye(3)):
        raise ValueError("prescribed displacements need supports without a rotated plane")
    from .discretize import _constrained_dofs
    from .model import Constrained

    dofs, vals = [], []
    for (name, comp), value_mm in prescribed.items():
        sd = _constrained_dofs(disc.skfem_basis, disc.mesh, Constrained(name, (comp,)))
        d = 3 * sd + comp
        if not disc.fixed[d].all():
            raise ValueError(f"prescribed component {comp} of node set {name!r} is not constrained")
        dofs.append(d)
        vals.append(np.full(d.size, value_mm * M_PER_MM))
    return np.concatenate(dofs), np.concatenate(vals)


def solve(
    model: Model,
    *,
    gravity: np.ndarray | None = None,
    g_m_s2: float = STANDARD_GRAVITY_M_S2,
    prescribed: dict | None = None,
    point_forces_n: dict | None = None,
    disc: Discretization | None = None,
    formulation: Formulation = "taylor-hood",
    options: SolverOptions | None = None,
    x0: np.ndarray | None = None,
    raise_on_failure: bool = True,
) -> Solution:
    """Static equilibrium of the model under gravity and prescribed displacements.

    Parameters
    ----------
    model : Model
        Mesh (mm), materials, densities and support.
    gravity : array_like, shape (3,), optional
        Gravity direction in the model frame (normalised here); ``None`` for none.
    g_m_s2 : float
        Gravitational acceleration magnitude in m/s^2.
    prescribed : dict, optional
        ``{(node_set, component): value_mm}``; the set must be ``Constrained``.
    point_forces_n : dict, optional
        ``{node_index: force (3,)}`` dead loads in N, model frame.
    disc : Discretization, optional
        Reuse a discretization of ``model.mesh`` (else one is built).
    formulation : {"p1", "p2", "mini", "taylor-hood"}
        Used when ``disc`` is not given.
    options : SolverOptions, optional
    x0 : ndarray, optional
        Warm start (``Solution.state`` of a solve on the same discretization); the full
        load is tried from it first, then load stepping from zero.
    raise_on_failure : bool
        Raise :class:`ConvergenceError` when the load cannot be applied (default),
        else return a solution with ``converged=False``.

    Returns
    -------
    Solution

    Raises
    ------
    ConvergenceError
        Newton fails at a load step below ``options.min_step`` and ``raise_on_failure``.
    ValueError
        ``prescribed`` names a component that is not constrained (or is combined with a
        sliding/elastic plane), ``x0`` has the wrong shape, or (``disc`` not given)
        ``formulation`` is unknown.
    MeshError
        From :func:`fem.discretize.discretize`, when ``disc`` is not given.
    """
    t_start = time.perf_counter()
    opts = options or SolverOptions()
    disc = disc or discretize(model.mesh, model.support, formulation=formulation)
    g = np.zeros(3) if gravity is None else gravity_vector(gravity, g_m_s2)
    f_ext = external_force(disc, model, g) + _point_forces(disc, point_forces_n)
    pres = _prescribed_dofs(disc, prescribed)
    stats = _Stats()
    prob = _Problem(disc, model, f_ext, opts, stats)
    if pres is not None:
        prob.f_scale = max(prob.f_scale, _reaction_scale(prob, pres))
    x, lam, steps, cuts, ok = _warm_or_stepped(prob, x0, pres, opts)
    if not ok and raise_on_failure:
        note, element = _stall(disc, model, x, lam, "the load")
        raise ConvergenceError(
            f"load not applied: Newton failed at a load step below {opts.min_step:g} "
            f"after {stats.newton} iterations ({cuts} cut-backs); {note}; "
            f"{_failure_cause(stats, lam, opts.rtol, float(np.ptp(disc.mesh.nodes_mm, 0).max()))}",
            element=element,
        )
    total = time.perf_counter() - t_start
    return Solution(
        displacement_mm=vertex_displacement_mm(disc, x),
        state=x,
        converged=ok,
        newton_iterations=stats.newton,
        load_steps=steps,
        cutbacks=cuts,
        residual_history=tuple(stats.history),
        timings_s={"assembly": stats.t_asm, "linear_solve": stats.t_lin, "total": total},
        dofs=int(disc.pattern.n_free),
        formulation=disc.formulation,
        factorizations=stats.factorizations,
    )


def _warm_or_stepped(prob: _Problem, x0, pres, opts: SolverOptions):
    if x0 is not None:
        if x0.shape != (prob.disc.n_dofs,):
            raise ValueError(f"x0 has shape {x0.shape}, expected ({prob.disc.n_dofs},)")
        x = _newton(prob, _apply_dirichlet(x0, pres, 1.0), 1.0)
        if x is not None:
            return x, 1.0, 1, 0, True
    return _load_steps(prob, np.zeros(prob.disc.n_dofs), pres, opts)


def _reaction_scale(prob: _Problem, pres) -> float:
    """Force scale for displacement-driven problems: the first-iteration reaction."""
    x = _apply_dirichlet(np.zeros(prob.disc.n_dofs), pres, 1.0)
    st = assemble(prob.disc, prob.model, np.zeros_like(x), tangent=True)
    K_full = _full_matrix(prob.disc, st.matrices)
    return float(np.linalg.norm(K_full @ x)) or 1.0


def _full_matrix(disc: Discretization, matrices: np.ndarray):
    import scipy.sparse as sp

    edofs = disc.element_dofs()
    n = edofs.shape[1]
    rows = np.repeat(edofs, n, axis=1).ravel()
    cols = np.tile(edofs, (1, n)).ravel()
    return sp.csr_matrix((matrices.ravel(), (rows, cols)), shape=(disc.n_dofs,) * 2)
