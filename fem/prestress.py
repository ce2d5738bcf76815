"""A prestressed reference: the loaded scan as the computational domain.

A scan shows the phantom under gravity ``g0``. Instead of recovering a stress-free mesh
and loading it again (:mod:`fem.unload`, which needs straight-sided stress-free elements
and fails where they degenerate at the clamped rim), the loaded geometry ``x_m`` itself
is the mesh and carries a *prestress*: a deformation gradient ``F0`` at every quadrature
point, from the (virtual) stress-free state to ``x_m``, whose stress balances ``g0``. A
posture change is then solved from ``x_m`` with ``F = F_d F0``, ``F_d = I + grad_x u``
(``u`` the displacement from the scan), and the loaded mesh never has to be inverted.

With ``dV = dv / J0`` (``J0 = det F0``) and ``delta F = grad_x(delta u) F0``, the weak
form on ``x_m`` is that of a total-Lagrangian body whose shape gradients are
``grad_x N F0`` and whose weights are ``w / J0`` (Eq. (1)); the deformation gradient is
``F0 + grad_x u F0`` (Eq. (2)). So the ordinary assembly serves, with the offset
``F0 - I`` added to ``F`` (Gee, Foerster & Wall 2010, Eqs. (13)-(17)). The body force is
``rho0 g dV`` (mass of the stress-free body).

Two ways to compute ``F0`` (``compute_prestress(method=...)``):

- ``"inverse"``: inverse elastostatics in spatial form (Govindjee & Mihalic 1996,
  1998): the unknown is the P2 field ``U`` on the loaded mesh with stress-free positions
  ``X = x - U``; ``F0 = (I - grad_x U)^-1`` is compatible (the gradient of a field). The
  equations are those of the forward problem on an *isoparametric* (curved) stress-free
  mesh whose loaded image is the straight-sided ``x_m``; Newton uses the exact Jacobian
  ``K - D`` with ``D`` the isoparametric shape derivative (:mod:`fem.shape_derivative`).
  Loading that curved stress-free mesh under ``g0`` gives back ``x_m`` exactly (the
  round trip), and every posture is its forward problem.
- ``"mulf"``: the modified updated Lagrangian formulation of Gee, Foerster & Wall (2010):
  ``g0`` is applied in load steps on the fixed geometry ``x_m``; after each converged step
  ``F0 <- (I + grad_x u) F0`` and the displacement is reset to zero (the geometry is
  never updated); at full load the update is repeated ("passes") until the displacement
  of a pass is below ``tol_mm``. The passes are a fixed point that contracts slowly on
  scan meshes (0.06 -> 0.036 mm in 25 passes on the 16 mm twin mesh), so their update is
  relaxed by Aitken's factor, ``F0 <- (I + omega grad_x u) F0`` (``omega = 1`` is Gee et
  al.'s; the 16 mm mesh then reaches 1e-6 mm in 16 passes). ``F0`` is then in
  equilibrium with ``g0`` on ``x_m`` but in general not compatible, and it depends on the
  load path: it is not the stress of any stress-free body, and it does not converge to
  the inverse's under mesh refinement (a clamped 40 mm box at 1 g: inverse and MULF
  postures differ by 0.05, 0.09, 0.13 mm RMS at h = 20, 10, 5 mm). MULF is the less
  robust of the two on scan meshes: its steps are forward solves on the loaded mesh,
  whose thin elements at the clamped rim accumulate extreme ``F0`` (on the 12 mm quick
  ``--effect none`` twin mesh with 10 load steps ``det F0`` spans 0.06-8e3 over the
  quadrature points), and there the passes at full load cannot be solved (with 4 or 10
  load steps): a :class:`ConvergenceError`. Use ``inverse`` where MULF fails.

Both solve different discrete problems from :mod:`fem.unload`'s ``newton`` (straight
stress-free elements, curved loaded ones): the answers agree to the discretisation
error, not to round-off (tests/fem/test_fem_prestress.py).

The derivative of positions in a material parameter (``ln c1`` in the calibration) is
:func:`prestress_sensitivity` (``dF0/dp``: for ``inverse`` one solve with ``K - D``, for
``mulf`` a forward sensitivity through the recorded load path, one solve per step) and
:func:`solve_prestressed_sensitivity` (``K du/dp = -dR/dp - dR/dF0 [dF0/dp]``).

References
----------
Gee, M. W., Foerster, Ch. & Wall, W. A. (2010). A computational strategy for prestressing
patient-specific biomechanical problems under finite deformation. *IJNMBE* 26, 52-72.
Govindjee, S. & Mihalic, P. A. (1996). Computational methods for inverse finite
elastostatics. *CMAME* 136, 47-57.
Govindjee, S. & Mihalic, P. A. (1998). Computational methods for inverse deformations in
quasi-incompressible finite elasticity. *IJNME* 43, 821-838.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from .assemble import _group, _n_loc, assemble, deformation_gradient, external_force, scatter
from .discretize import Discretization, Formulation, discretize
from .fields import gravity_vector, vertex_displacement_mm
from .linalg import factorize
from .model import Model
from .sensitivity import parameter_derivative
from .shape_derivative import geometry_matrices
from .solver import (
    ConvergenceError,
    Solution,
    SolverOptions,
    _newton,
    _Problem,
    _Stats,
    merit,
    merit_weights,
    newton_step,
    solve,
    stall_note,
)
from .units import MM_PER_M, STANDARD_GRAVITY_M_S2

__all__ = [
    "Prestress",
    "PrestressMethod",
    "compute_prestress",
    "dof_positions_mm",
    "isoparametric_discretization",
    "node_displacement_mm",
    "prestress_sensitivity",
    "prestressed_residual",
    "PostureSolve",
    "round_trip_mm",
    "RETRY_OPTIONS",
    "solve_posture",
    "solve_prestressed",
    "solve_prestressed_sensitivity",
    "stress_free_discretization",
    "stress_free_node_positions_mm",
]

log = logging.getLogger(__name__)

PrestressMethod = Literal["inverse", "mulf"]
_EYE = np.eye(3)


@dataclass(frozen=True)
class Prestress:
    """The prestress of a loaded mesh: result of :func:`compute_prestress`.

    Attributes
    ----------
    F0 : ndarray, shape (E, Q, 3, 3)
        Deformation gradient from the stress-free state to the loaded mesh at every
        quadrature point of the formulation (solver frame).
    state : ndarray, shape (n_dofs,)
        The reference equilibrium in prestressed form: zero displacement, the pressure
        field of the mixed formulations (solver units). Starts every posture solve.
    method : {"inverse", "mulf"}
    compatible : bool
        ``F0`` is the gradient of a displacement field (``inverse``).
    gravity_m_s2 : ndarray, shape (3,)
        The gravity vector ``g0`` it balances, model frame.
    formulation : str
    converged : bool
        Always True for a returned object (failures raise :class:`ConvergenceError`).
    load_steps : int
        Successful load increments (``mulf``: including the passes at full load).
    newton_iterations : int
    residual_displacement_mm : float
        ``inverse``: largest node distance from the scan of the curved stress-free mesh
        loaded by ``g0`` in the forward solver's own assembly
        (:func:`isoparametric_discretization`, no ``F0``), warm-started at the recovered
        state: ~0 when the two assemblies agree to Newton's tolerance (a round trip from
        zero displacement is in the tests and the benchmark; at a clamped rim with
        degenerate curved elements it can settle on another equilibrium, 0.094 mm off at
        nodes within 0.75 mm of the back in ``tests/fem/test_fem_reference_robust.py``).
        ``mulf``: largest vertex displacement of the last pass (the equilibrium defect of
        ``F0`` on ``x_m``).
    stress_free_nodes_mm : ndarray, shape (n_nodes, 3) or None
        ``inverse``: stress-free vertex positions, model frame, mm (the curved mesh's
        vertices). None for ``mulf`` (no stress-free mesh exists).
    inverse_state : ndarray, shape (n_dofs,) or None
        ``inverse``: the solver vector ``U`` (``X = x - U`` at every P2 node), for warm
        starts and sensitivities.
    path : tuple of (float, ndarray)
        ``mulf``: the load factor and converged step displacement of every step (for
        :func:`prestress_sensitivity`); empty for ``inverse``.
    wall_s : float
    """

    F0: np.ndarray
    state: np.ndarray
    method: str
    compatible: bool
    gravity_m_s2: np.ndarray
    formulation: str
    converged: bool
    load_steps: int
    newton_iterations: int
    residual_displacement_mm: float
    stress_free_nodes_mm: np.ndarray | None = None
    inverse_state: np.ndarray | None = None
    path: tuple = ()
    wall_s: float = 0.0

    @property
    def J0(self) -> np.ndarray:
        """``det F0`` at every quadrature point, (E, Q)."""
        return np.linalg.det(self.F0)


# -- the prestressed body --------------------------------------------------------------


def _virtual(disc0: Discretization, F0: np.ndarray, J0: np.ndarray) -> Discretization:
    """Eq. (1): gradients ``grad_x N F0`` and weights ``w / J0`` on the loaded mesh."""
    grad = np.einsum("eqai,eqij->eqaj", disc0.grad_u, F0, optimize=True)
    return replace(disc0, grad_u=grad, weights=disc0.weights / J0)


def _assemble(disc_v, model: Model, x: np.ndarray, offset: np.ndarray, tangent: bool):
    """Residual vectors (and tangents) with ``F = I + grad_X u + offset`` (Eq. (2))."""
    F = deformation_gradient(disc_v, x) + offset
    n_loc = _n_loc(disc_v)
    min_J = float(np.linalg.det(F).min())
    if min_J <= 0:
        return None, None
    vec = np.zeros((len(F), n_loc))
    mat = np.zeros((len(F), n_loc, n_loc)) if tangent else None
    for idx, material, _ in model.element_material_groups():
        r, K, _ = _group(disc_v, x, F, idx, material, tangent)
        vec[idx] = r
        if tangent:
            mat[idx] = K
    return vec, mat


def prestressed_residual(
    disc0: Discretization,
    model: Model,
    F0: np.ndarray,
    state: np.ndarray,
    gravity_m_s2: np.ndarray,
) -> np.ndarray:
    """Full residual ``R_int - f_ext`` of the prestressed body at a state, (n_dofs,).

    Parameters
    ----------
    disc0 : Discretization
        Of the loaded mesh.
    model : Model
    F0 : ndarray, shape (E, Q, 3, 3)
    state : ndarray, shape (n_dofs,)
        Displacement from the loaded mesh and pressure (solver units).
    gravity_m_s2 : ndarray, shape (3,)
        Gravity vector, model frame (:func:`fem.fields.gravity_vector`).

    Returns
    -------
    ndarray
        NaN everywhere when some ``det F <= 0``.
    """
    J0 = np.linalg.det(F0)
    disc_v = _virtual(disc0, F0, J0)
    vec, _ = _assemble(disc_v, model, state, F0 - _EYE, tangent=False)
    if vec is None:
        return np.full(disc0.n_dofs, np.nan)
    return scatter(disc_v, vec) - external_force(disc_v, model, gravity_m_s2)


class _Prestressed(_Problem):
    """``R_int(x; F0) - f0 - lam (f - f0) = 0``: from the reference load ``f0`` to ``f``.

    ``f0`` is the load the prestress balances (zero when ``F0`` is being built), so
    ``lam = 0`` is the reference state and load stepping stays meaningful.
    """

    def __init__(self, disc0, model, F0, g_ref, g_new, opts, stats):
        _no_springs(disc0)
        J0 = np.linalg.det(F0)
        if J0.min() <= 0:
            raise ValueError("prestress F0 has det <= 0 at some quadrature point")
        self.disc_v = _virtual(disc0, F0, J0)
        self.offset = F0 - _EYE
        f = external_force(self.disc_v, model, g_new)
        f0 = external_force(self.disc_v, model, g_ref) if g_ref is not None else 0.0 * f
        super().__init__(disc0, model, f - f0, opts, stats)
        self.f0 = f0
        # convergence relative to the whole gravity load, not to its change
        self.f_scale = max(np.linalg.norm(f), np.linalg.norm(f0), 1e-300)

    def residual(self, x, lam, tangent):
        t0 = time.perf_counter()
        vec, mat = _assemble(self.disc_v, self.model, x, self.offset, tangent)
        self.stats.t_asm += time.perf_counter() - t0
        if vec is None:
            return None, None
        r = scatter(self.disc_v, vec) - self.f0 - lam * self.f_ext
        K = self.disc.pattern.matrix(mat) if tangent else None
        return r[self.free], K

    def linear_solve(self, K, r, m: float):
        """Newton step; the prestressed tangent is symmetric (conservative loads)."""
        return newton_step(self, K, r, m, symmetric=True)


def _stepped(prob: _Problem, x, opts: SolverOptions):
    """Adaptive load stepping from ``lam = 0`` to 1 from ``x``; (x, lam, steps, cuts, ok)."""
    lam, dlam, steps, cuts = 0.0, opts.initial_step, 0, 0
    for _ in range(opts.max_steps):
        trial = min(1.0, lam + dlam)
        n0 = prob.stats.newton
        new = _newton(prob, x, trial)
        if new is None:
            cuts += 1
            dlam *= 0.25
            if dlam < opts.min_step:
                return x, lam, steps, cuts, False
            continue
        x, lam, steps = new, trial, steps + 1
        if lam >= 1.0:
            return x, lam, steps, cuts, True
        dlam = min(dlam * (2.0 if prob.stats.newton - n0 <= 5 else 1.0), 1.0 - lam)
    return x, lam, steps, cuts, False


def solve_prestressed(
    model: Model,
    prestress: Prestress,
    *,
    gravity: np.ndarray | None,
    g_m_s2: float = STANDARD_GRAVITY_M_S2,
    disc: Discretization | None = None,
    options: SolverOptions | None = None,
    x0: np.ndarray | None = None,
    raise_on_failure: bool = True,
) -> Solution:
    """Equilibrium of the prestressed loaded mesh under another gravity.

    Parameters
    ----------
    model : Model
        On the loaded mesh (the mesh ``prestress`` was computed on), mm.
    prestress : Prestress
    gravity : array_like, shape (3,), or None
        Gravity direction of the posture, model frame; None for no gravity.
    g_m_s2 : float
        Its magnitude, m/s^2.
    disc : Discretization, optional
        Of ``model.mesh`` (reused across calls; else built).
    options : SolverOptions, optional
    x0 : ndarray, shape (n_dofs,), optional
        Warm start (a previous ``Solution.state`` of this posture); the full load is
        tried from it first, then load stepping from the reference state.
    raise_on_failure : bool
        Raise :class:`ConvergenceError` when the load cannot be applied.

    Returns
    -------
    Solution
        ``displacement_mm`` relative to the loaded mesh (model frame, mm): the posture's
        vertex positions are ``model.mesh.nodes_mm + displacement_mm``.

    Raises
    ------
    ConvergenceError
        Newton fails at a load step below ``options.min_step`` and ``raise_on_failure``.
    ValueError
        ``prestress`` does not belong to ``disc`` (quadrature shape or formulation), or
        its ``F0`` has ``det <= 0`` at some quadrature point.
    """
    t_start = time.perf_counter()
    opts = options or SolverOptions()
    disc = disc or discretize(model.mesh, model.support, formulation=prestress.formulation)
    _check_shape(disc, prestress)
    g = np.zeros(3) if gravity is None else gravity_vector(gravity, g_m_s2)
    stats = _Stats()
    prob = _Prestressed(disc, model, prestress.F0, prestress.gravity_m_s2, g, opts, stats)
    x, lam, steps, cuts, ok = None, 0.0, 0, 0, False
    if x0 is not None:
        x = _newton(prob, np.asarray(x0, float).copy(), 1.0)
        steps, ok = (1, True) if x is not None else (0, False)
    if x is None:
        x, lam, steps, cuts, ok = _stepped(prob, prestress.state.copy(), opts)
    if not ok and raise_on_failure:
        where = stall_note(disc, model, x, lam, load="the change from the reference load")
        raise ConvergenceError(
            f"prestressed load not applied: Newton failed at a load step below "
            f"{opts.min_step:g} after {stats.newton} iterations ({cuts} cut-backs); {where}"
        )
    return _solution(disc, x, ok, stats, steps, cuts, t_start)


def _solution(disc, x, ok, stats, steps, cuts, t_start) -> Solution:
    return Solution(
        displacement_mm=vertex_displacement_mm(disc, x),
        state=x,
        converged=ok,
        newton_iterations=stats.newton,
        load_steps=steps,
        cutbacks=cuts,
        residual_history=tuple(stats.history),
        timings_s={
            "assembly": stats.t_asm,
            "linear_solve": stats.t_lin,
            "total": time.perf_counter() - t_start,
        },  # fmt: skip
        dofs=int(disc.pattern.n_free),
        formulation=disc.formulation,
        factorizations=stats.factorizations,
    )


def _no_springs(disc: Discretization) -> None:
    if disc.spring is not None:
        raise ValueError(
            "the prestressed reference supports clamped, sliding (rim held) and constrained "
            "supports; springs (ElasticSupport, Sliding with tangent stiffness) would carry "
            "a force in the reference state that is not modelled"
        )


def _failure(message: str, load_factor: float, iterations: int) -> ConvergenceError:
    """A :class:`ConvergenceError` carrying ``load_factor`` and ``iterations``."""
    err = ConvergenceError(message)
    err.load_factor, err.iterations = load_factor, iterations
    return err


def _check_shape(disc: Discretization, prestress: Prestress) -> None:
    if prestress.F0.shape[:2] != disc.weights.shape or disc.formulation != prestress.formulation:
        raise ValueError(
            f"prestress of shape {prestress.F0.shape[:2]} ({prestress.formulation}) does not "
            f"belong to this discretization ({disc.weights.shape}, {disc.formulation})"
        )


# -- inverse elastostatics in spatial form ---------------------------------------------


def _inverse_F0(disc0: Discretization, U: np.ndarray):
    """``F0 = (I - grad_x U)^-1`` and ``det F0``; None where ``det(I - grad_x U) <= 0``."""
    f = 2.0 * _EYE - deformation_gradient(disc0, U)  # I - grad_x U
    det_f = np.linalg.det(f)
    if det_f.min() <= 0:
        return None, None
    return np.linalg.inv(f), 1.0 / det_f


class _SpatialInverse:
    """``R(U; X = x - U) = lam f(X)`` on the isoparametric stress-free mesh.

    The residual is assembled on the virtual (curved) reference of Eq. (1) with
    ``F = F0 = I + grad_X U``; the Jacobian is ``K - D`` with ``D`` the isoparametric
    shape derivative. Same interface as the forward solver's problems.
    """

    def __init__(self, model: Model, disc0: Discretization, g_vec, opts: SolverOptions):
        self.model, self.disc0, self.g, self.opts = model, disc0, g_vec, opts
        self.free = disc0.free
        self.stats = _Stats()
        self.f_scale = max(np.linalg.norm(external_force(disc0, model, g_vec)), 1e-300)
        self.v_scale = float(disc0.weights.sum())
        self.u_free = disc0.free < 3 * disc0.n_scalar_u
        self.factor = None

    def disc(self, U):
        F0, J0 = _inverse_F0(self.disc0, U)
        return None if F0 is None else _virtual(self.disc0, F0, J0)

    def residual(self, U, lam, tangent: bool):
        t0 = time.perf_counter()
        d = self.disc(U)
        if d is None:
            return None, None
        st = assemble(d, self.model, U, tangent=tangent)
        if st.min_J <= 0:
            return None, None
        g = lam * self.g
        r = scatter(d, st.vectors) - external_force(d, self.model, g)
        M = None
        if tangent:
            D = geometry_matrices(d, self.model, U, g, geometry="isoparametric")
            M = d.pattern.matrix(st.matrices - D)
        self.stats.t_asm += time.perf_counter() - t0
        return r[self.free], M

    def merit(self, r) -> float:
        return merit(r, self.u_free, self.f_scale, self.v_scale, self.disc0.mixed)

    @property
    def scale(self) -> np.ndarray:
        """Row weights of the free residual whose norm is :meth:`merit`."""
        return merit_weights(self.u_free, self.f_scale, self.v_scale)

    def linear_solve(self, M, r, m: float):
        """Newton step; the inverse problem's Jacobian is not symmetric."""
        return newton_step(self, M, r, m, symmetric=False)


def _inverse(model, disc0, g_vec, opts, x0_state):
    prob = _SpatialInverse(model, disc0, g_vec, opts)
    if x0_state is not None:
        warm = _newton(prob, np.asarray(x0_state, float).copy(), 1.0)
        if warm is not None:
            return warm, 1, prob
    U, lam, steps, cuts, ok = _stepped(prob, np.zeros(disc0.n_dofs), opts)
    if not ok:
        raise _failure(
            f"stress-free reference not recovered (spatial inverse): stopped at load factor "
            f"{lam:.3g} after {prob.stats.newton} iterations in {steps} load steps with {cuts} "
            f"cut-backs (limits {opts.max_steps} steps, smallest step {opts.min_step:g})",
            lam,
            prob.stats.newton,
        )
    return U, steps, prob


def isoparametric_discretization(disc0: Discretization, nodes_mm: np.ndarray) -> Discretization:
    """The discretization of ``disc0``'s topology on curved (isoparametric) elements.

    Parameters
    ----------
    disc0 : Discretization
        A discretization (its reference-element data, dofs and support are reused).
    nodes_mm : ndarray, shape (n_scalar_u, 3)
        Position of every displacement node (P2: vertices and edge nodes, in the order
        of the scalar dofs), model frame, mm.

    Returns
    -------
    Discretization
        Gradients and weights from the element map ``X(xi) = sum_a X_a N_a(xi)`` at each
        quadrature point; ``mesh`` holds the vertices. A check of :mod:`fem.prestress`'s
        ``inverse`` method independent of ``F0`` (the round trip), and the stress-free
        mesh of it.

    Raises
    ------
    ValueError
        When the element map has ``det <= 0`` at a quadrature point.
    """
    R = disc0.R_solver_from_model
    X = (np.asarray(nodes_mm, float) / MM_PER_M) @ R.T  # solver frame, m
    ref = disc0.reference_data
    grad_ref, w_ref = ref["grad"], ref["weights"]  # (Q, A, 3) in xi, (Q,)
    jac = np.einsum("eai,qam->eqim", X[disc0.udofs], grad_ref, optimize=True)
    det = np.linalg.det(jac)
    if det.min() <= 0:
        raise ValueError(f"{int((det <= 0).any(axis=1).sum())} curved elements are inverted")
    grad = np.einsum("qam,eqmj->eqaj", grad_ref, np.linalg.inv(jac), optimize=True)
    vertices = np.asarray(nodes_mm, float)[disc0.skfem_basis.nodal_dofs[0]]
    mesh = disc0.mesh.with_nodes(vertices)
    return replace(disc0, mesh=mesh, grad_u=grad, weights=det * w_ref[None, :])


def stress_free_discretization(disc: Discretization, prestress: Prestress) -> Discretization:
    """The curved stress-free mesh of an ``inverse`` prestress, ready for :func:`fem.solve`.

    Parameters
    ----------
    disc : Discretization
        Of the loaded mesh the prestress was computed on.
    prestress : Prestress
        With ``method="inverse"``.

    Returns
    -------
    Discretization
        Isoparametric (:func:`isoparametric_discretization`) on the stress-free positions
        ``X = x - U`` of every displacement node; ``.mesh.nodes_mm`` holds its vertices.
        Loading it by ``g0`` from zero gives back the loaded mesh (the round trip),
        unless degenerate curved elements at a clamped rim let it settle on another
        equilibrium there (:class:`Prestress`, ``residual_displacement_mm``).
    """
    return isoparametric_discretization(disc, stress_free_node_positions_mm(disc, prestress))


def stress_free_node_positions_mm(disc: Discretization, prestress: Prestress) -> np.ndarray:
    """Stress-free position of every displacement node of an ``inverse`` prestress.

    Parameters
    ----------
    disc : Discretization
        Of the loaded mesh the prestress was computed on.
    prestress : Prestress
        With ``method="inverse"``.

    Returns
    -------
    ndarray, shape (n_scalar_u, 3)
        Model frame, mm, in the order of the scalar displacement dofs (P2: vertices,
        then edge nodes); rows ``disc.skfem_basis.nodal_dofs[0]`` are
        ``prestress.stress_free_nodes_mm``.
    """
    if prestress.inverse_state is None:
        raise ValueError(f"a {prestress.method!r} prestress has no stress-free mesh")
    _check_shape(disc, prestress)
    return _dof_positions_mm(disc) - node_displacement_mm(disc, prestress.inverse_state)


def dof_positions_mm(disc: Discretization, state: np.ndarray | None = None) -> np.ndarray:
    """Positions (mm, model frame) of the displacement nodes of a straight-sided mesh.

    Parameters
    ----------
    disc : Discretization
        With affine elements (``fem.discretize``, not :func:`isoparametric_discretization`).
    state : ndarray, shape (n_dofs,), optional
        A solver vector whose displacement is added.

    Returns
    -------
    ndarray, shape (n_scalar_u, 3)
        In the order of the scalar displacement dofs.
    """
    X = _dof_positions_mm(disc)
    return X if state is None else X + node_displacement_mm(disc, state)


def _dof_positions_mm(disc0: Discretization) -> np.ndarray:
    """Model-frame positions (mm) of the scalar displacement dofs on ``disc0.mesh``'s nodes.

    Vertices, edge midpoints (P2) and element centroids (MINI's bubble); from the
    current vertices, so it holds for ``Discretization.with_nodes`` too.
    """
    b, mesh = disc0.skfem_basis, disc0.mesh
    X = np.zeros((disc0.n_scalar_u, 3))
    X[b.nodal_dofs[0]] = mesh.nodes_mm
    if b.edge_dofs.size:
        X[b.edge_dofs[0]] = mesh.nodes_mm[b.mesh.edges].mean(axis=0)
    if b.interior_dofs.size:
        X[b.interior_dofs[0]] = mesh.nodes_mm[mesh.tets].mean(axis=1)
    return X


def node_displacement_mm(disc: Discretization, x: np.ndarray) -> np.ndarray:
    """Displacement (mm, model frame) of every displacement node from a solver vector.

    Parameters
    ----------
    disc : Discretization
    x : ndarray, shape (n_dofs,)

    Returns
    -------
    ndarray, shape (n_scalar_u, 3)
        In the order of the scalar displacement dofs (vertices: ``nodal_dofs[0]``).
    """
    u = x[: 3 * disc.n_scalar_u].reshape(-1, 3)
    return u @ disc.R_solver_from_model * MM_PER_M


# -- MULF ------------------------------------------------------------------------------


def _internal_force(prob: _Prestressed, x: np.ndarray) -> np.ndarray:
    vec, _ = _assemble(prob.disc_v, prob.model, x, prob.offset, tangent=False)
    if vec is None:
        raise ConvergenceError("MULF: an element is inverted after the prestress update")
    return scatter(prob.disc_v, vec)


def _mulf(model, disc0, g_vec, opts, tol_mm, max_passes, n_steps):
    """Gee et al. (2010), Sect. 3: load steps on the fixed geometry, ``F0 <- F_d F0``.

    Each step (and each pass at full load) starts from the reset state, which is out of
    balance with the new load level; the imbalance is applied in sub-steps
    (``R_int - r0 - mu (f - r0) = 0``, ``r0`` the internal force at the reset state, ``mu``
    from 0 to 1) with cut-backs. Returns ``(F0, x, path, stats, cuts, last, lam, ok)``.
    """
    F0 = np.broadcast_to(_EYE, disc0.weights.shape + (3, 3)).copy()
    x = np.zeros(disc0.n_dofs)
    nu = 3 * disc0.n_scalar_u
    stats, path = _Stats(), []
    lam, dlam, cuts, passes, last = 0.0, 1.0 / n_steps, 0, 0, np.inf
    omega, r_old = 1.0, None
    while passes < max_passes and len(path) < opts.max_steps + max_passes:
        target = min(1.0, lam + dlam)
        prob = _Prestressed(disc0, model, F0, None, target * g_vec, opts, stats)
        prob.f0 = _internal_force(prob, x)
        prob.f_ext = prob.f_ext - prob.f0
        new, _, _, sub_cuts, ok = _stepped(prob, x, opts)
        cuts += sub_cuts
        if not ok:
            if lam >= 1.0 or dlam / 4 < opts.min_step:
                return F0, x, path, stats, cuts, last, lam, False
            dlam /= 4
            continue
        if lam >= 1.0:  # a pass: Aitken's relaxation of the update
            omega = _aitken_omega(omega, r_old, new[:nu])
            r_old = new[:nu].copy()
        path.append((target, new.copy(), omega))
        # Eq. (2): F0 <- F_d F0, F_d = I + omega grad_x u (omega = 1: Gee et al.)
        F0 = F0 + omega * (deformation_gradient(prob.disc_v, new) - _EYE)
        last = float(np.abs(vertex_displacement_mm(disc0, new)).max())
        x = new.copy()
        x[:nu] = 0.0  # the geometry is never updated; the pressure is kept
        if lam >= 1.0:
            passes += 1
            log.info("MULF pass %d: largest displacement %.3g mm (omega %.3g)", passes, last,
                     omega)  # fmt: skip
            if last <= tol_mm:
                return F0, x, path, stats, cuts, last, lam, True
        lam = target
    return F0, x, path, stats, cuts, last, lam, False


def _aitken_omega(omega: float, r_old, r_new) -> float:
    """Aitken's adaptive relaxation of a fixed point's increments (Irons & Tuck 1969)."""
    if r_old is None:
        return 1.0
    d = r_new - r_old
    denom = float(d @ d)
    if denom == 0.0:
        return omega
    return float(np.clip(-omega * float(r_old @ d) / denom, 0.2, 20.0))


# -- the public entry point ------------------------------------------------------------


def compute_prestress(
    model: Model,
    *,
    gravity: np.ndarray,
    g_m_s2: float = STANDARD_GRAVITY_M_S2,
    formulation: Formulation = "taylor-hood",
    method: PrestressMethod = "inverse",
    disc: Discretization | None = None,
    options: SolverOptions | None = None,
    x0_state: np.ndarray | None = None,
    tol_mm: float = 1e-6,
    max_passes: int = 50,
    load_steps: int = 4,
) -> Prestress:
    """The prestress that holds the loaded mesh in equilibrium under ``g0``.

    Parameters
    ----------
    model : Model
        ``model.mesh`` is the loaded (scanned) geometry, mm; materials and densities of
        the stress-free body.
    gravity : array_like, shape (3,)
        Direction of ``g0``, model frame.
    g_m_s2 : float
        Its magnitude.
    formulation : {"p1", "p2", "mini", "taylor-hood"}
        Used when ``disc`` is not given.
    method : {"inverse", "mulf"}
        See the module docstring.
    disc : Discretization, optional
        Of ``model.mesh`` (reused across calls).
    options : SolverOptions, optional
        Newton and load-step controls (``max_steps`` bounds the load steps).
    x0_state : ndarray, shape (n_dofs,), optional
        ``inverse``: warm start, ``Prestress.inverse_state`` of a nearby material (the
        full load is tried from it first).
    tol_mm : float
        ``mulf``: stop the passes at full load when the largest vertex displacement of a
        pass is below this.
    max_passes : int
        ``mulf``: most passes at full load.
    load_steps : int
        ``mulf``: equal load steps up to ``g0`` (quartered where one fails); the
        prestress depends on this path.

    Returns
    -------
    Prestress

    Raises
    ------
    ConvergenceError
        The load could not be applied within ``options.max_steps`` load steps, or (``mulf``)
        the passes did not settle within ``max_passes``; the message says how far it got.
    """
    t0 = time.perf_counter()
    if method not in ("inverse", "mulf"):
        raise ValueError(f"unknown prestress method {method!r}; choose inverse or mulf")
    opts = options or SolverOptions()
    disc0 = disc or discretize(model.mesh, model.support, formulation=formulation)
    _no_springs(disc0)
    g_vec = gravity_vector(gravity, g_m_s2)
    nu = 3 * disc0.n_scalar_u
    if method == "mulf":
        F0, x, path, stats, cuts, last, lam, ok = _mulf(
            model, disc0, g_vec, opts, tol_mm, max_passes, load_steps
        )
        if not ok:
            raise _failure(
                f"MULF prestress not converged: load factor {lam:.3g} after {stats.newton} "
                f"iterations in {len(path)} steps ({cuts} cut-backs), last step displacement "
                f"{last:.3g} mm (tol {tol_mm:g} mm, limits {opts.max_steps} steps, "
                f"{max_passes} passes)",
                lam,
                stats.newton,
            )
        return Prestress(F0, x, "mulf", False, g_vec, disc0.formulation, True, len(path),
                         stats.newton, last, path=tuple(path),
                         wall_s=time.perf_counter() - t0)  # fmt: skip
    U, steps, prob = _inverse(model, disc0, g_vec, opts, x0_state)
    F0, _ = _inverse_F0(disc0, U)
    state = U.copy()
    state[:nu] = 0.0
    X_dofs = _dof_positions_mm(disc0) - node_displacement_mm(disc0, U)
    err = _round_trip_mm(model, disc0, X_dofs, U, g_vec, opts)
    X = X_dofs[disc0.skfem_basis.nodal_dofs[0]]
    return Prestress(F0, state, "inverse", True, g_vec, disc0.formulation, True, steps,
                     prob.stats.newton, err, stress_free_nodes_mm=X, inverse_state=U,
                     wall_s=time.perf_counter() - t0)  # fmt: skip


def round_trip_mm(
    model: Model,
    prestress: Prestress,
    *,
    warm_start: bool = False,
    options: SolverOptions | None = None,
) -> float:
    """Load the curved stress-free mesh of an inverse prestress by its ``g0``: its distance.

    The recovered stress-free geometry checked in the forward solver's own assembly,
    independent of ``F0``: :func:`stress_free_discretization` loaded by
    ``prestress.gravity_m_s2`` (:func:`fem.solve`).

    Parameters
    ----------
    model : Model
        On the loaded mesh the prestress was computed on.
    prestress : Prestress
        With ``method="inverse"``.
    warm_start : bool
        Start Newton at the recovered state (``prestress.inverse_state``), as the
        recovery's own check (``residual_displacement_mm``) does; False (default): from
        zero displacement, the whole load path from rest.
    options : SolverOptions, optional

    Returns
    -------
    float
        Largest distance (mm) of any displacement node (P2: edge nodes too) of the loaded
        curved mesh from its place on the loaded mesh. From rest, degenerate curved
        elements at a clamped rim can settle on another equilibrium than the recovered
        one (:class:`Prestress`, ``residual_displacement_mm``).

    Raises
    ------
    ValueError
        A ``mulf`` prestress (no stress-free mesh exists).
    ConvergenceError
        The forward solve has no solution.
    """
    if prestress.stress_free_nodes_mm is None:
        raise ValueError(f"a {prestress.method} prestress has no stress-free mesh to load")
    disc0 = discretize(model.mesh, model.support, formulation=prestress.formulation)
    X_dofs = stress_free_node_positions_mm(disc0, prestress)
    x0 = prestress.inverse_state if warm_start else None
    return _round_trip_mm(
        model, disc0, X_dofs, x0, prestress.gravity_m_s2, options or SolverOptions()
    )


def _round_trip_mm(model, disc0, X_dofs_mm, U, g_vec, opts) -> float:
    """Load the curved stress-free mesh by ``g0`` (independent of ``F0``): distance to x_m.

    ``U``: the Newton start (None: zero displacement).
    """
    from .solver import solve

    iso = isoparametric_discretization(disc0, X_dofs_mm)
    sol = solve(model.with_mesh(iso.mesh), gravity=g_vec, g_m_s2=float(np.linalg.norm(g_vec)),
                disc=iso, options=opts, x0=U)  # fmt: skip
    loaded = X_dofs_mm + node_displacement_mm(iso, sol.state)
    return float(np.linalg.norm(loaded - _dof_positions_mm(disc0), axis=1).max())


# -- sensitivities ---------------------------------------------------------------------


def _direction_derivative(disc0, model_at, p, F0, dF0, state, g_vec, eps=1e-6):
    """``d/de R(state; F0 + e dF0, p + e)`` at e = 0 by central differences, (n_dofs,).

    ``dF0 = None`` differentiates in ``p`` alone. The residual is smooth in both, so the
    difference error is O(eps^2) relative (as :func:`fem.sensitivity.parameter_derivative`).
    """
    dF = 0.0 if dF0 is None else dF0
    rp = prestressed_residual(disc0, model_at(p + eps), F0 + eps * dF, state, g_vec)
    rm = prestressed_residual(disc0, model_at(p - eps), F0 - eps * dF, state, g_vec)
    return (rp - rm) / (2.0 * eps)


def _tangent(disc0, model, F0, state):
    J0 = np.linalg.det(F0)
    disc_v = _virtual(disc0, F0, J0)
    _, mat = _assemble(disc_v, model, state, F0 - _EYE, tangent=True)
    return disc0.pattern.matrix(mat)


def prestress_sensitivity(
    model_at,
    p: float,
    prestress: Prestress,
    *,
    disc: Discretization | None = None,
) -> np.ndarray:
    """``dF0/dp``: the derivative of the prestress in a model parameter.

    Parameters
    ----------
    model_at : callable
        ``model_at(p) -> Model`` on the loaded mesh (e.g. ``p = ln c1``).
    p : float
        The parameter value ``prestress`` was computed at.
    prestress : Prestress
    disc : Discretization, optional
        Of the loaded mesh.

    Returns
    -------
    ndarray, shape (E, Q, 3, 3)
        ``inverse``: from ``(K - D) dU/dp = -dR/dp`` (one factorisation) and
        ``dF0 = F0 grad_x(dU) F0``. ``mulf``: the forward sensitivity of the recorded load
        path, ``K_k du_k = -dR_k/dp - dR_k/dF0 [dF0_(k-1)]``,
        ``dF0_k = grad_x(du_k) F0_(k-1) + F_d,k dF0_(k-1)`` (one factorisation per step):
        the exact derivative of the algorithm as run.
    """
    model = model_at(p)
    disc0 = disc or discretize(model.mesh, model.support, formulation=prestress.formulation)
    _check_shape(disc0, prestress)
    g = prestress.gravity_m_s2
    if prestress.method == "inverse":
        U = prestress.inverse_state
        F0, J0 = _inverse_F0(disc0, U)
        d = _virtual(disc0, F0, J0)
        Ke = assemble(d, model, U, tangent=True).matrices
        Ke = Ke - geometry_matrices(d, model, U, g, geometry="isoparametric")
        rhs = -parameter_derivative(d, model_at, p, U, g)
        dU = np.zeros(disc0.n_dofs)
        dU[disc0.free] = factorize(d.pattern.matrix(Ke))(rhs[disc0.free])
        gdU = deformation_gradient(disc0, dU) - _EYE
        return F0 @ gdU @ F0
    F0 = np.broadcast_to(_EYE, disc0.weights.shape + (3, 3)).copy()
    dF0 = np.zeros_like(F0)
    for lam, u, omega in prestress.path:
        rhs = -_direction_derivative(disc0, model_at, p, F0, dF0, u, lam * g)
        du = np.zeros(disc0.n_dofs)
        K = _tangent(disc0, model, F0, u)
        du[disc0.free] = factorize(K, symmetric=True)(rhs[disc0.free])
        Fd = _EYE + omega * (deformation_gradient(disc0, u) - _EYE)  # I + omega grad_x u
        dF0 = omega * (deformation_gradient(disc0, du) - _EYE) @ F0 + Fd @ dF0
        F0 = Fd @ F0
    return dF0


#: Solver options of the retry after a failed posture solve: small load steps from a
#: cold start (the calibration's postures and the sweeps' scenarios alike).
RETRY_OPTIONS = SolverOptions(initial_step=0.125, min_step=1e-3, max_newton=15, max_steps=40)


@dataclass(frozen=True)
class PostureSolve:
    """Result of :func:`solve_posture`.

    Attributes
    ----------
    solution : Solution
    retried : str or None
        Why the first attempt failed (None when it converged).
    failed_newton : int
        Newton iterations of the failed first attempt (0 when none failed).
    """

    solution: Solution
    retried: str | None = None
    failed_newton: int = 0


def _newton_of(exc: Exception) -> int:
    """Newton iterations a :class:`ConvergenceError`'s message reports (0 if none)."""
    import re

    m = re.search(r"after (\d+) iterations", str(exc))
    return int(m.group(1)) if m else 0


def solve_posture(
    model: Model,
    *,
    gravity: np.ndarray | None,
    g_m_s2: float,
    disc: Discretization,
    prestress: Prestress | None = None,
    x0: np.ndarray | None = None,
    retry: bool = True,
    retry_options: SolverOptions = RETRY_OPTIONS,
) -> PostureSolve:
    """One posture: the full load from a warm start, then small load steps if that fails.

    On ``disc`` with :func:`fem.solve` (a stress-free reference), or with
    :func:`solve_prestressed` when ``prestress`` is given (the loaded mesh carrying it).

    Parameters
    ----------
    model : Model
        On ``disc.mesh``, mm.
    gravity : array_like, shape (3,), or None
        Gravity direction, model frame.
    g_m_s2 : float
    disc : Discretization
    prestress : Prestress, optional
    x0 : ndarray, optional
        Warm start (a previous ``Solution.state`` of this posture).
    retry : bool
        Retry a failed first attempt with ``retry_options`` from a cold start.
    retry_options : SolverOptions

    Returns
    -------
    PostureSolve

    Raises
    ------
    ConvergenceError
        The first attempt failed and ``retry`` is False, or the retry failed too.
    """
    kw = {"gravity": gravity, "g_m_s2": g_m_s2, "disc": disc}

    def run(**extra) -> Solution:
        if prestress is not None:
            return solve_prestressed(model, prestress, **kw, **extra)
        return solve(model, **kw, **extra)

    try:
        return PostureSolve(run(x0=x0))
    except ConvergenceError as exc:
        if not retry:
            raise
        return PostureSolve(run(options=retry_options), str(exc), _newton_of(exc))


def solve_prestressed_sensitivity(
    model_at,
    p: float,
    prestress: Prestress,
    dF0: np.ndarray,
    solution: Solution,
    *,
    gravity: np.ndarray | None,
    g_m_s2: float = STANDARD_GRAVITY_M_S2,
    disc: Discretization | None = None,
) -> np.ndarray:
    """``du/dp`` of a converged posture of :func:`solve_prestressed` (full vector).

    Solves ``K du = -dR/dp - dR/dF0 [dF0]`` with the posture's tangent (one
    factorisation); the vertex positions' derivative is
    ``fem.fields.vertex_displacement_mm(disc, du)`` (the loaded mesh does not move).

    Parameters
    ----------
    model_at : callable
        ``model_at(p) -> Model`` on the loaded mesh.
    p : float
    prestress : Prestress
    dF0 : ndarray, shape (E, Q, 3, 3)
        :func:`prestress_sensitivity`.
    solution : Solution
        The posture's solution at ``p``.
    gravity, g_m_s2
        The posture's gravity, as given to :func:`solve_prestressed`.
    disc : Discretization, optional
    """
    model = model_at(p)
    disc0 = disc or discretize(model.mesh, model.support, formulation=prestress.formulation)
    g = np.zeros(3) if gravity is None else gravity_vector(gravity, g_m_s2)
    x = solution.state
    rhs = -_direction_derivative(disc0, model_at, p, prestress.F0, dF0, x, g)
    du = np.zeros(disc0.n_dofs)
    K = _tangent(disc0, model, prestress.F0, x)
    du[disc0.free] = factorize(K, symmetric=True)(rhs[disc0.free])
    return du
